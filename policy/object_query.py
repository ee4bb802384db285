"""The object query: where a long task's later grasp takes its object from and puts it, asked of an object locator
at the start and given to the policy while that grasp cycle runs.

Why: drawer_put opens the drawer, takes the object into it and shuts it. Run as those skills (runtime/phases.py)
the policy opens the drawer 19 times in 20, but its head, trained mostly on the approach to a handle, points back
at the handle once the drawer is open: none of 20 episodes then holds the object. Given the object's and the
drop's true points in that middle cycle the same denoiser completes 9 of 20 (policy/EXPERIMENTS.md, "drawer_put
as three skills the policy has"). The object lies on the table where it started until it is taken, and the
drawer does not move on the cabinet, so both points can be found before anything moves: an object locator
(policy/goal_locator.py, the "object" question: a copy of the policy's encoders and head taught on rendered
at-home views of the object stage) is asked the command on the first `ticks` inferences, and the median of its
answers (base frame) is held and given as the grasp and release points (`Bundle.act(grasp=..., release=...)`)
while the grasp cycles counted since the start (policy/stage.py) equal `stage`; the other cycles keep the head's.

Torch-free: the runtime's policy node and `sudd eval` use it through the bundle; `sudd export ... --object-query
FAMILY --object-query-data DATA --object-locator RUN` measures and records it (the manifest's `object_query`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.goal_query import query_table

MAX_TICKS = 20


@dataclass(frozen=True)
class ObjectQuerySpec:
    """The manifest's `object_query`: which families use it, in which grasp cycle its points are given, and for
    how many first inferences the locator is asked."""

    families: tuple[str, ...]
    stage: int
    ticks: int


def object_query_spec(manifest: dict) -> ObjectQuerySpec | None:
    """The validated `object_query` of a manifest, None where it has none; a ValueError names the field."""
    q = query_table(manifest, "object_query", "grasp_input", "grasp point")
    if q is None:
        return None
    families = q["families"]
    stage, ticks = q.get("stage"), q.get("ticks")
    if not (isinstance(stage, int) and 1 <= stage <= 8):
        raise ValueError(f"manifest object_query.stage {stage!r}: expected the grasp cycle it serves, an integer in "
                         "[1, 8] (drawer_put's object: 1)")
    if not (isinstance(ticks, int) and 1 <= ticks <= MAX_TICKS):
        raise ValueError(f"manifest object_query.ticks {ticks!r}: expected an integer in [1, {MAX_TICKS}]")
    return ObjectQuerySpec(tuple(families), stage, ticks)


class ObjectQuery:
    """One command's object query (module doc); inactive (`inputs` gives nothing) where the bundle has none, the
    family is not listed, or `enabled` is False."""

    def __init__(self, bundle, text: str, family: str | None, enabled: bool = True):
        spec = getattr(bundle, "object_query", None)  # a torch stand-in (policy.oracle_eval) has none
        self.active = bool(enabled and spec is not None and family in spec.families)
        self.bundle, self.spec = bundle, spec
        self._command = bundle.embed(text) if self.active else None  # asked the command, whatever the phase says
        self.answers: list[np.ndarray] = []
        self.points: np.ndarray | None = None  # (2, 3): the object and where it goes, base frame [m]

    def inputs(self, images: dict, proprio: np.ndarray, stage: int) -> dict:
        """`Bundle.act`'s grasp and release for this inference ({} for the head's own): the locator is asked
        on the first `ticks` inferences, its held answer given while `stage` grasp cycles are done."""
        if not self.active:
            return {}
        if len(self.answers) < self.spec.ticks:
            self.answers.append(self.bundle.object_points(images, proprio, self._command))
            self.points = np.median(np.stack(self.answers), axis=0)
        if stage != self.spec.stage:
            return {}
        flag = np.ones((2, 1), np.float32)
        grasp, release = np.hstack([self.points.astype(np.float32), flag])
        return {"grasp": grasp, "release": release}
