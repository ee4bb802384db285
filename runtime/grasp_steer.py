"""The grasp steer: after the fingers close on nothing, the policy's next approach is moved over the object that the
object query located (policy/object_query.py), for as long as that query serves its grasp cycle.

Why: the denoiser hardly follows the grasp point it is given (the bundle's `grasp_gain`: 0.1 cm per cm, against 0.7
for the release point), so a policy that misses a cylinder misses it again at the same place: drawer_stow seed
100600 closed three times 6.5-7.3 cm from the cylinder while the object locator's answer lay 0.5 cm from it. Of
step 36's 200 drawer_stow episodes on seeds 100500-100699, 21 closed on nothing at least once and 17 of those
failed (policy/EXPERIMENTS.md, "The grasp steer"). A first grasp is left to the policy (the locator is off by more than
3.8 cm in one episode in ten); a retry is where the policy has shown it is off.

How: fed the gripper's position request and measured closure each tick, it notes a miss: a close (request at or
above policy.stage.CLOSED) whose fingers measured at or beyond EMPTY_CLOSED (nothing between them) within MISS_S of
its start (later, it is an object slipping out of fingers that held it, not a grasp that missed). After a miss,
while the fingers are commanded open and the grasp cycle is the object query's, a chunk that ends low near the
located object (below its centre + REACH_UP_M, between MIN_OFFSET_M and MAX_OFFSET_M from it horizontally) is moved
horizontally so that it ends over the object, eased in over EASE_S so that its first action moves little. Heights,
turns and the gripper channel stay the policy's. A chunk that ends far from the object (the policy heading
elsewhere) or high above it is left alone.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import CLOSED
from runtime.controller.gripper import EMPTY_CLOSED

MIN_OFFSET_M = 0.015  # nearer than this the policy's own aim stands (the locator's median error is 1 cm)
MAX_OFFSET_M = 0.10  # further than this the policy is after something else
REACH_UP_M = 0.08  # a chunk ending higher than this above the object's centre is not yet going for it
EASE_S = 0.3  # the move reaches its full size this far into the chunk
MISS_S = 2.0  # s: the 2F-85 closes its whole stroke in under 1 s


class GraspSteer:
    """One command's grasp steer (module doc); inactive where `enabled` is False."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.misses = 0  # closes on nothing in the current grasp cycle
        self.steered = 0  # chunks moved
        self._stage: int | None = None
        self._close_start: float | None = None  # when the standing close began (None: commanded open)
        self._counted = False  # the standing close's miss is counted

    def update(self, command: float, closure: float, stage: int, now: float) -> None:
        """Feed the gripper's position request and measured closure (0 open .. 1 closed), the grasp cycles
        completed (policy.stage.GraspCycles) and the time [s] at this tick."""
        if stage != self._stage:
            self._stage, self.misses = stage, 0
        if command < CLOSED:
            self._close_start, self._counted = None, False
            return
        if self._close_start is None:
            self._close_start = now
        if not self._counted and closure >= EMPTY_CLOSED and now - self._close_start <= MISS_S:
            self.misses += 1
            self._counted = True

    def chunk(self, actions: np.ndarray, objects, stage: int, command: float, dt: float) -> np.ndarray:
        """The chunk (n, 10: position, rot6d, gripper; base frame) to play, one action every `dt` s: moved over the
        object `objects` (policy.object_query.ObjectQuery) located, or as it was (module doc)."""
        if not (self.enabled and self.misses and objects.active and stage == objects.stage
                and objects.points is not None and command < 0.5):
            return actions
        target = np.asarray(objects.points[0], np.float64)
        end = np.asarray(actions[-1, :3], np.float64)
        gap = target[:2] - end[:2]
        if end[2] > target[2] + REACH_UP_M or not MIN_OFFSET_M < float(np.hypot(*gap)) < MAX_OFFSET_M:
            return actions
        ease = np.minimum(1.0, (np.arange(len(actions)) + 1) * dt / EASE_S)
        out = np.array(actions, copy=True)
        out[:, :2] += (ease[:, None] * gap).astype(out.dtype)
        self.steered += 1
        return out


__all__ = ["GraspSteer"]
