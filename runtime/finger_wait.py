"""The arm waits for the fingers: while they are still closing (or opening) as the chunk asks, it holds its pose.

Why: the shipped bundle's data gripper is not the runtime's. Its collector set the 2F-85 model's finger servo at
once (`sudd datagen --gripper servo`; the default now moves them as the twin does, sim/finger_drive.py), and the
fingers met an object within 0.1 s of the close; it then held still 0.6 s and lifted (datagen.primitives'
GRASP_SECONDS). The runtime's gripper, like the real one, moves its fingers at the commanded speed (the controller's
`gripper_speed`, 80 mm/s: 0.65 s to close on a 4 cm block through the SimGripper twin). So the policy, which learned
to lift about 0.5 s after it asks for a close, lifts while the fingers are still closing: they meet the object when
the TCP is already near its top, a grasp on the pads' lowest few millimetres that slips out on the way to the drawer
(drawer_stow seed 100502: closed 2.5 cm above a 4.3 cm cylinder's centre, dropped at 25 cm/s; policy/EXPERIMENTS.md,
"The arm waits for the fingers"). Holding the arm where it is while the measured closure still moves the way the
chunk asks gives the grasp the data had: fingers closed on the object before it lifts.

A hold lasts until the fingers stop (their measured closure changes slower than `Wait.moving` per second between
the last tick's newest observation and this tick's) or `Wait.most_s`, whichever is first: fingers that never
stop do not freeze the arm. A chunk that asks the gripper the other way (a close undone) is played as it is. numpy
only: the runtime's policy node and `sudd eval` both use it, on the policy's own chunks (not a look's or a
retreat's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policy.stage import GRIPPER_COLUMN as GRIPPER

POSE = slice(0, GRIPPER)  # an action's and a proprio step's TCP position and rot6d


@dataclass(frozen=True)
class Wait:
    moving: float = 0.1  # closure change per second that counts as the fingers moving (a close runs at ~0.9 / s)
    most_s: float = 1.5  # the longest one wait holds the arm [s] (the full stroke at 20 mm/s is 4 s: a stuck finger)


class FingerWait:
    """One command's waits for the fingers (module doc). The closure's change is read between this tick's newest
    observation and the last tick's: a bundle may observe a single step."""

    def __init__(self, cfg: Wait = Wait(), enabled: bool = True):
        self.cfg, self.enabled = cfg, enabled
        self._last: tuple[float, float] | None = None  # (time, closure) of the last tick's newest observation
        self._since: float | None = None  # when the standing wait began
        self.held = 0  # chunks replaced by a hold

    def rate(self, closure: float, t: float) -> float:
        """The fingers' closure change per second since the last tick (0 at the first, or at the same time)."""
        last, self._last = self._last, (t, closure)
        if last is None or t <= last[0]:
            return 0.0
        return (closure - last[1]) / (t - last[0])

    def chunk(self, actions: np.ndarray, proprio: np.ndarray, t: float) -> np.ndarray:
        """The policy's (n, Da) chunk observed at `t` [s], `proprio` the newest observation step (D,): a hold of
        its pose, with the chunk's gripper requests, while the fingers still move the way the chunk asks (module
        doc); else `actions` itself."""
        closure = float(proprio[GRIPPER])
        rate = self.rate(closure, t)
        asked = float(actions[0, GRIPPER]) - closure
        if not (self.enabled and abs(rate) > self.cfg.moving and asked * rate > 0.0):
            self._since = None
            return actions
        if self._since is None:
            self._since = t
        if t - self._since > self.cfg.most_s:
            return actions
        self.held += 1
        out = np.array(actions, copy=True)
        out[:, POSE] = np.asarray(proprio)[POSE]
        return out
