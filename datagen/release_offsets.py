"""Where the placed object sits in the hand as the gripper opens: the episode meta's `release_offsets`.

Why: the recorded release point is where the TCP let go. With the object off the TCP in the hand (a grasp that
closed off centre), the collector lets go beside the target so that the object lands on it (Primitives.place
plans from the object's live pose in the hand). A policy told "release here" learns nothing about the hand from
such an episode; told where the object goes (the TCP's point moved by the object's offset: policy config
`release_point = "object"`), it must read the offset from the wrist camera to land the object, the one skill
the distilled policy's stack failures lack (policy/EXPERIMENTS.md, "Stack's placing failures are off-centre
grasps, not early let-gos").

Each entry: the recorded step whose action is the first with the gripper open (datagen.schema's release step),
the object's name and its origin minus the TCP, base frame [m], one physics step into the opening, when the
fingers have not yet moved it.
"""

from __future__ import annotations

import numpy as np

RELEASE_LABEL = "release"


class ReleaseOffsets:
    """Wraps the episode's recorder as `datagen.trajectory.execute`'s observer for a place motion, and keeps
    one entry per release it sees (module doc)."""

    def __init__(self, recorder, world):
        self.recorder, self.world = recorder, world
        self.records: list[dict] = []

    def placing(self, obj: str):
        """The observer for a motion that places `obj`: the recorder's, with the offset taken as the release
        segment starts."""
        body = self.world.model.body(obj).id
        last = [None]

        def observe(world, label: str = "", *planned) -> None:
            if label == RELEASE_LABEL and last[0] != RELEASE_LABEL:
                offset = np.asarray(world.data.xpos[body]) - world.tcp_pose()[:3, 3]
                # the action of step t is the target of step t + 1: the next sample is the first with the
                # gripper told to open, so the release step is the one before it
                self.records.append({"step": max(self.recorder.steps - 1, 0), "object": obj,
                                     "offset_m": [round(float(v), 5) for v in offset]})
            last[0] = label
            self.recorder(world, label, *planned)

        return observe


def release_offset_at(records: list[dict] | None, step: int, tolerance: int = 2) -> np.ndarray | None:
    """The recorded offset (3,) [m] of the release nearest `step`, within `tolerance` steps, else None."""
    if not records:
        return None
    best = min(records, key=lambda r: abs(int(r["step"]) - int(step)))
    if abs(int(best["step"]) - int(step)) > tolerance:
        return None
    return np.asarray(best["offset_m"], np.float64)


__all__ = ["RELEASE_LABEL", "ReleaseOffsets", "release_offset_at"]
