"""Where the fingers hold the block: the release point moved by the block's offset from the TCP.

Why: step 33's stack episodes that let the block go 2 cm or more off the TCP stacked 13 times in 26, against
97 % of those that held it within 1 cm; the chunk had aimed the TCP well (policy/EXPERIMENTS.md, "Stack's
placing failures are off-centre grasps"). The goal query gives the denoiser where the *block* should go, and
the denoiser puts the TCP there, as every recorded episode could: the collector grasps near the centre.

How: at the look (runtime/look.py) the goal locator is also asked the command as given, not role-swapped:
taught to find the first-named block, it then finds the block to pick up (`GoalQuery.object_point`). When the
fingers have come to rest on something (measured closure between HELD and AIR, still for two steps), the
block's offset from the TCP across the pads (the TCP's y axis; the fingers centre it along x, the closing
axis) is taken from that point and held in the gripper's frame; every later inference is given the release
point minus that offset turned with the TCP as it is now. The offset is dropped when the fingers open, and
only the first hold of a command takes one: once lifted, the block is no longer where the look saw it (a
re-grasp after a miss took stale offsets of 2-3 cm in 3 of 240 episodes, each a lost stack).

Numpy only: the runtime's policy node and `sudd eval` use it through policy.goal_query.
"""

from __future__ import annotations

import numpy as np

from policy.action_frame import rotations
from policy.stage import AIR, GRIPPER_COLUMN

HELD = 0.2  # measured closure above this and below AIR: the fingers stopped on something (a 2F-85 closure)
LET_GO = 0.1  # and below this again: open
STILL = 0.01  # closure change between the two observation steps under which the fingers are at rest
MAX_OFFSET_M = 0.03  # further across the pads than this is no block held between them: the point was wrong


class HandOffset:
    """The held block's offset from the TCP, across the pads, from a point where its centre was (module doc)."""

    def __init__(self) -> None:
        self.across_m: float | None = None  # along the TCP's y axis, metres; None while nothing is held
        self.taken: list[float] = []  # the offset taken this command, if any (for the evaluation's records)

    def update(self, proprio: np.ndarray, object_point: np.ndarray | None) -> None:
        """Feed an inference's (To, Dp) proprio (TCP pos, rot6d, closure, ...), oldest first."""
        p = np.asarray(proprio, np.float64)
        closure = p[-1, GRIPPER_COLUMN]
        if closure < LET_GO:
            self.across_m = None
            return
        still = abs(closure - p[-2, GRIPPER_COLUMN]) < STILL if len(p) > 1 else True
        if self.taken or object_point is None or not (HELD < closure < AIR and still):
            return
        y_axis = rotations(p[-1, 3:9])[:, 1]
        across = float(np.dot((np.asarray(object_point, np.float64) - p[-1, :3])[:2], y_axis[:2]))
        if abs(across) <= MAX_OFFSET_M:
            self.across_m = across
            self.taken.append(round(across, 4))

    def shift(self, point: np.ndarray, proprio: np.ndarray) -> np.ndarray:
        """The release point for the TCP: `point` (where the block should go) minus the held offset, turned with
        the TCP's yaw now (unchanged while nothing is held)."""
        if self.across_m is None:
            return point
        y_axis = rotations(np.asarray(proprio, np.float64)[-1, 3:9])[:, 1]
        out = np.array(point, np.float64)
        out[:2] -= self.across_m * y_axis[:2]
        return out.astype(np.asarray(point).dtype)
