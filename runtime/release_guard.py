"""The release guard: while the fingers hold the object of the object query's grasp cycle, the policy's opening is
held back where the arm is far from the drop point that query gives and high above where the object lay, so that the
object is not let go in the air on its way.

Why: the denoiser decides to let go by the height and the look of the scene as much as by where the drop is, and now
and then it opens over the wrong place: drawer_stow seed 100602 lifted the block 13 cm above where it lay and let it
go right there, 24 cm from the drawer; it fell back onto the table and the arm went on to the drawer empty. Of step
37's 200 drawer_stow episodes, 9 let their object go in the air more than 10 cm from the drawer (policy/EXPERIMENTS.md,
"The release guard"). A put-down is left alone: the policy sets a poorly held object back on the table to take it
again (12 of those 200 episodes do, and complete), and such an opening comes with the hand low, at the object's
resting height.

How: in the object query's grasp cycle, with its points known, while the fingers are commanded closed and measure
less than EMPTY_CLOSED (something is between them), each action of the chunk that asks them open (below
policy.stage.CLOSED) at a point more than FAR_M from the drop horizontally and more than LOW_M above the object's
located centre gets the standing request instead. The arm's motion stays the policy's; the next chunk, given the
same drop point, carries the object on. Every action still goes through the safety layer.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import CLOSED, GRIPPER_COLUMN
from runtime.controller.gripper import EMPTY_CLOSED

FAR_M = 0.10  # horizontally from the drop: the drawer's cavity is about 14 cm across, the locator 2 cm off (median)
LOW_M = 0.04  # above the object's resting centre: lower than this the hand is putting the object down, not dropping it


class ReleaseGuard:
    """One command's release guard (module doc); inactive where `enabled` is False."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.held = 0  # chunks whose opening was held back

    def chunk(self, actions: np.ndarray, objects, stage: int, command: float, closure: float) -> np.ndarray:
        """The chunk (n, 10; base frame) with its openings far from the drop held back, or as it was (module doc).
        `objects` is the command's policy.object_query.ObjectQuery; `command` and `closure` the gripper's standing
        position request and measured closure (0 open .. 1 closed); `stage` the grasp cycles completed."""
        if not (self.enabled and objects.active and stage == objects.stage and objects.points is not None
                and command >= CLOSED and closure < EMPTY_CLOSED):
            return actions
        drop, rest_z = objects.drop, float(objects.points[0][2])
        pos = np.asarray(actions[:, :3], np.float64)
        held = ((np.asarray(actions[:, GRIPPER_COLUMN]) < CLOSED) & (pos[:, 2] > rest_z + LOW_M)
                & (np.hypot(pos[:, 0] - drop[0], pos[:, 1] - drop[1]) > FAR_M))
        if not held.any():
            return actions
        out = np.array(actions, copy=True)
        out[held, GRIPPER_COLUMN] = command
        self.held += 1
        return out


__all__ = ["ReleaseGuard"]
