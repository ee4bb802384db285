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
while the grasp cycles counted since the start (policy/stage.py) equal `stage`; the other cycles keep the head's,
except that a family listed in `keep_release` still gets the drop point in the cycles after (ObjectQuerySpec).

The release point given is the locator's plus the manifest's `release_shift_m` (base frame, default none). Why:
the locator is taught the middle of the drawer's cavity (datagen.view_anchors.drop_point), which with the drawer
85-100 % open lies only 1.7-4 cm in front of the cabinet; the collector reaches down into it, but the policy lets
go over the rim, and a release 2-3 cm behind its aim holds the object over the cabinet's top, where the object
lands (drawer_stow seed 100562: the fingers' opening held 8 s by the top's keep-out box, then the object rested on
the top). The drawers of the scenes the bundle learned open towards the robot (-y), so a shift that way moves the
release over the open part; measured in closed loop, `sudd export --object-release-shift` records it
(policy/EXPERIMENTS.md, "The drop moved out from under the cabinet's top").

Torch-free: the runtime's policy node and `sudd eval` use it through the bundle; `sudd export ... --object-query
FAMILY --object-query-data DATA --object-locator RUN` measures and records it (the manifest's `object_query`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.goal_query import check_xyz, parse_xyz, query_table

MAX_TICKS = 20
MAX_SHIFT_M = 0.1  # per axis: a release shift further than this is no nudge over the drawer's open part


@dataclass(frozen=True)
class ObjectQuerySpec:
    """The manifest's `object_query`: which families use it, in which grasp cycle its points are given, and for
    how many first inferences the locator is asked."""

    families: tuple[str, ...]
    stage: int
    ticks: int
    # A family whose object grasp comes at another cycle: drawer_stow takes its object first (0), as drawer_put's
    # middle phase that it is (runtime/phases.py), where drawer_put takes it after the handle (1).
    family_stage: tuple[tuple[str, int], ...] = ()
    release_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)  # added to the locator's release point [m]
    # Families whose grasp cycles after the query's still get its drop point (not its object point: the object has
    # moved): in drawer_stow a later cycle is the same object taken again to the same drawer, after it was let go
    # elsewhere; drawer_put's next cycle is the handle. Without it the retry ran on the head's drop, 13 cm in front
    # (policy/EXPERIMENTS.md, "The drop kept for the retry").
    keep_release: tuple[str, ...] = ()

    def stage_of(self, family: str | None) -> int:
        return dict(self.family_stage).get(family, self.stage)


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
    by_family = q.get("family_stage", {})
    if not (isinstance(by_family, dict) and all(f in families and isinstance(k, int) and 0 <= k <= 8
                                                and not isinstance(k, bool) for f, k in by_family.items())):
        raise ValueError(f"manifest object_query.family_stage {by_family!r}: expected a table of its families to "
                         "the grasp cycle each is served in, integers in [0, 8] (drawer_stow's object: 0)")
    shift = q.get("release_shift_m", [0.0, 0.0, 0.0])
    keep = check_keep_release(q.get("keep_release", []), families, "manifest object_query.keep_release")
    return ObjectQuerySpec(tuple(families), stage, ticks, tuple(sorted(by_family.items())),
                           check_release_shift(shift, "manifest object_query.release_shift_m"), keep)


def check_release_shift(shift, where: str) -> tuple[float, float, float]:
    """A release shift (dx, dy, dz) in metres, base frame, checked (policy.goal_query.check_xyz)."""
    return check_xyz(shift, where, MAX_SHIFT_M, "(base frame)")


def check_keep_release(keep, families, where: str) -> tuple[str, ...]:
    """The families (a list, each served by the query) whose later grasp cycles keep its drop point."""
    if not (isinstance(keep, (list, tuple)) and all(isinstance(f, str) and f in families for f in keep)):
        raise ValueError(f"{where} {keep!r}: expected a list of the families the object query serves "
                         f"({', '.join(families)}) whose later grasp cycles keep its drop point, e.g. drawer_stow")
    return tuple(dict.fromkeys(keep))


def parse_release_shift(text: str) -> tuple[float, float, float]:
    """"DX,DY,DZ" (metres) -> a checked release shift."""
    return parse_xyz(text, "--object-release-shift", MAX_SHIFT_M, "(base frame)", "0,-0.03,0")


def with_skill_families(table: dict, tasks) -> dict:
    """The object query `table` extended to the families among `tasks` that are a phase of a family it serves
    (policy.phased.SKILL_PHASE): drawer_stow is drawer_put's middle phase, the same object taken from the same
    table with the drawer open, so the same locator answers it, given in its first grasp cycle (0)."""
    from policy.phased import SKILL_PHASE

    families, by_family = list(table["families"]), dict(table.get("family_stage", {}))
    for served in table["families"]:
        for skill in SKILL_PHASE.get(served, {}).values():
            if skill in tasks and skill not in families:
                families.append(skill)
                by_family[skill] = 0
    return {**table, "families": families, **({"family_stage": by_family} if by_family else {})}


class ObjectQuery:
    """One command's object query (module doc); inactive (`inputs` gives nothing) where the bundle has none, the
    family is not listed, or `enabled` is False."""

    def __init__(self, bundle, text: str, family: str | None, enabled: bool = True):
        spec = getattr(bundle, "object_query", None)  # a torch stand-in (policy.oracle_eval) has none
        self.active = bool(enabled and spec is not None and family in spec.families)
        self.bundle, self.spec = bundle, spec
        self.stage = spec.stage_of(family) if spec is not None else None  # the grasp cycle it serves
        self.keeps_release = self.active and family in spec.keep_release  # and the drop in the cycles after it
        self._command = bundle.embed(text) if self.active else None  # asked the command, whatever the phase says
        self.answers: list[np.ndarray] = []
        self.points: np.ndarray | None = None  # (2, 3): the object and where it goes, base frame [m]

    def inputs(self, images: dict, proprio: np.ndarray, stage: int) -> dict:
        """`Bundle.act`'s grasp and release for this inference ({} for the head's own): the locator is asked
        on the first `ticks` inferences, its held answer given while `stage` grasp cycles are done, and its drop
        alone after that in a family that keeps it (ObjectQuerySpec.keep_release)."""
        if not self.active:
            return {}
        if len(self.answers) < self.spec.ticks:
            self.answers.append(self.bundle.object_points(images, proprio, self._command))
            self.points = np.median(np.stack(self.answers), axis=0)
        if stage < self.stage or (stage > self.stage and not self.keeps_release):
            return {}
        grasp = np.append(self.points[0], 1.0).astype(np.float32)
        release = np.append(self.drop, 1.0).astype(np.float32)
        return {"grasp": grasp, "release": release} if stage == self.stage else {"release": release}

    @property
    def drop(self) -> np.ndarray | None:
        """(3,) the drop point given to the policy (the locator's, shifted by the manifest's release_shift_m), base
        frame [m]; None before the locator has answered."""
        if self.points is None:
            return None
        return (self.points[1].astype(np.float32) + np.asarray(self.spec.release_shift, np.float32))
