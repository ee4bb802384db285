"""The empty close: fingers that have stood shut on nothing for a while are opened where they are, as the data
collector reopens after a missed grasp.

Why: the collector, its fingers closed on air, holds GRASP_SECONDS (0.6 s), finds the grasp missed and opens the
gripper where it is (datagen.primitives.reopen), so its data never shows a hand shut on nothing for long. The
policy in that state is where its data never was, and it stays there: drawer_close 100504 held its fingers shut on
nothing for 9.6 s, drawer_put 100587 and 100606 for 8.8 and 9.2 s, before they opened or the episode ran out
(policy/EXPERIMENTS.md, "The empty close").

How: once the fingers have measured shut on nothing (closure at or above policy.stage.AIR, the 2F-85 fully closed)
under a closed request (at or above CLOSED) for HOLD_S, every row of the chunk that asks them closed asks them open
(0) instead, until they measure less than shut; the arm's poses stay the policy's, so the next grasp goes on from
where the hand is, as the collector's retry does. A close on nothing is no grasp cycle (policy.stage.GraspCycles),
so the policy is told the same stage after it. Every action still goes through the safety layer.

numpy only: the runtime's policy node and `sudd eval` both use it.
"""

from __future__ import annotations

import numpy as np

from policy.stage import AIR, CLOSED, GRIPPER_COLUMN

HOLD_S = 1.0  # shut on nothing this long: the collector's 0.6 s hold and its check, with some to spare


class EmptyClose:
    """One command's empty-close reopening (module doc); inactive where `enabled` is False."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.since: float | None = None  # when the fingers last began to stand shut on nothing [s]
        self.opened = 0  # chunks whose closed rows were asked open

    def chunk(self, actions: np.ndarray, request: float, closure: float, t: float) -> np.ndarray:
        """The chunk (n, 10) with its closed rows asked open once the fingers have stood shut on nothing for
        HOLD_S, or as it was (module doc). `request` and `closure` the gripper's standing position request and
        measured closure (0 open .. 1 closed); `t` [s] the observation's time."""
        if not (request >= CLOSED and closure >= AIR):
            self.since = None
        elif self.since is None:
            self.since = t
        if not (self.enabled and self.since is not None and t - self.since >= HOLD_S - 1e-9):
            return actions
        closed = actions[:, GRIPPER_COLUMN] >= CLOSED
        if not closed.any():
            return actions
        out = actions.copy()
        out[closed, GRIPPER_COLUMN] = 0.0
        self.opened += 1
        return out


__all__ = ["EmptyClose", "HOLD_S"]
