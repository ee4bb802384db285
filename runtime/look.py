"""A look before the command: the arm moves to the goal query's look pose, the query is asked there, and the arm
goes back to the start before the policy's first chunk.

Why: stack's goal locator is asked where the block to stack on is, on the first frames, the arm at home. From
home the wrist camera misses the table's far right (x > ~0.2 m): 18 of step 32's 120 evaluation scenes have the
lower block outside its view, where the scene camera shows it ~5 px wide, and 11 of those 18 answers were more
than 4 cm off (8 of them failed; of the other 102 scenes one answer was). From the start pose moved
(0.15, 0.08, 0.10) m the wrist camera sees every object of every stack scene with 20 px to spare
(policy/EXPERIMENTS.md, "A look before stacking"). The locator is taught on views from that pose (`sudd views
--look`), and the bundle's manifest records the pose (goal_query.look_m), so the question is asked of the view
it learned.

The moves are `runtime.retreat`'s: up first, then across, turning on the way (here the orientation is kept), at
its speeds, through the controller and the safety filter like any chunk. The query is asked once the TCP is
within `reach` of the look pose and has stood there `settle` seconds; after `max_seconds` without getting there
the look is given up and the policy runs with its head's own release point (GoalQuery.release gives none). The
arm then goes back to where it started, where the policy's training episodes begin.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from runtime.retreat import Retreat, hold_chunk, retreat_chunk


class Look:
    """One command's look (module doc); inactive (`active` False from the start) where its goal query has no
    look pose."""

    def __init__(self, query, cfg: Retreat = Retreat(max_seconds=10.0)):
        self.query, self.cfg = query, cfg
        self.offset = np.asarray(query.spec.look_m, np.float64) if query.look else None
        self.state = "done" if self.offset is None else "go"
        self.start: np.ndarray | None = None  # (9,) the TCP pose the command started from
        self.seconds = 0.0  # spent looking, back included
        self._still = 0.0  # seconds at the look pose so far
        self.gave_up = False

    @property
    def active(self) -> bool:
        return self.state != "done"

    def chunk(self, images: dict, proprio: np.ndarray, gripper: float, n: int, dt: float) -> np.ndarray | None:
        """(n, 10) actions for this tick, or None once the look is over (the policy's turn). `proprio`: the window
        (To, Dp) whose newest row's first 9 columns are the TCP pose; `gripper`: the hand's position request,
        held throughout; `dt`: seconds between actions (one tick runs `dt` of the chunk before the next call)."""
        if not self.active:
            return None
        pose = np.asarray(proprio[-1, :9], np.float64)
        if self.start is None:
            self.start = pose.copy()
        target = self.start.copy()
        target[:3] += self.offset
        self.seconds += dt
        if self.state in ("go", "ask") and self.seconds > self.cfg.max_seconds:
            self.state, self.gave_up = "back", True
        if self.state == "go":
            if _there(pose, target, self.cfg):
                self._still += dt
                if self._still >= self.cfg.settle:
                    self.state = "ask"
            else:
                self._still = 0.0
            if self.state == "go":
                return retreat_chunk(pose, target, gripper, n, dt, self.cfg)
        if self.state == "ask":
            self.query.ask(images, proprio)
            if self.query.settled:
                self.state = "back"
            else:
                return hold_chunk(target, n, gripper)
        if _there(pose, self.start, self.cfg) or self.seconds > 2 * self.cfg.max_seconds:
            self.state = "done"
            return None
        return retreat_chunk(pose, self.start, gripper, n, dt, self.cfg)


def _there(pose: np.ndarray, target: np.ndarray, cfg: Retreat) -> bool:
    return float(np.linalg.norm(pose[:3] - target[:3])) <= cfg.reach
