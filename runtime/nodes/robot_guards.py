"""What stands between the robot node's controller and the arm: the bypass check, and a no-motion stand-in.

Every servo_j goes through `GuardedArm`, which checks that the target it is given is exactly the safety
filter's latest output (`GuardedFilter` records it); a mismatch would be a bypass and is counted (`bypass`,
expected 0) and refused. `Hold` takes the ControllerLoop's place on hardware without `allow_motion`: it
accepts no chunk and commands nothing.
"""

from __future__ import annotations

import numpy as np


class GuardedFilter:
    """The SafetyFilter, with the output of its latest step recorded (for GuardedArm's check)."""

    def __init__(self, inner):
        self._inner = inner
        self.last_q: np.ndarray | None = None
        self.steps = 0

    def step(self, *args, **kw):
        r = self._inner.step(*args, **kw)
        self.last_q = np.array(r.q, dtype=float)
        self.steps += 1
        return r

    def __getattr__(self, name):
        return getattr(self._inner, name)


class GuardedArm:
    """The arm, whose servo_j only passes the safety filter's latest output (anything else: a bypass)."""

    def __init__(self, inner, guard: GuardedFilter):
        self._inner, self._guard = inner, guard
        self.servo_sent = 0
        self.bypass = 0

    def servo_j(self, q, *args, **kw):
        ref = self._guard.last_q
        if ref is None or not np.array_equal(np.asarray(q, dtype=float), ref):
            self.bypass += 1
            return False
        self.servo_sent += 1
        return self._inner.servo_j(q, *args, **kw)

    def __getattr__(self, name):
        return getattr(self._inner, name)


class Hold:
    """Hardware without allow_motion: stands in for the controller; never commands anything."""

    state = "hold_no_motion"
    stopped = True

    def submit(self, chunk) -> bool:
        return False

    def estop(self, reason: str = "") -> None: ...

    def drain_events(self) -> list:
        return []

    def start(self) -> None: ...

    def stop(self) -> bool:
        return True

    class telemetry:  # noqa: N801 - mimics ControllerLoop.telemetry
        @staticmethod
        def summary() -> dict:
            return {}
