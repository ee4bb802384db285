"""Protective-stop recovery, driven once per cycle: the robot's report -> safety's stop state machine -> hooks.

Why here and not in the filter: the filter's StopStateMachine says what to do next (notify, wait, unlock,
re-arm, await confirmation) but cannot talk to the robot or the operator. This walks it through with the
arm driver and two operator hooks, never raising (a hook that fails is an event; recovery waits):

* `notify(message)`: tell the operator (UI, log); called once per stop.
* `confirm() -> operator id | None`: polled while the machine awaits confirmation; returning a non-empty id
  confirms. Operators can also call `ControllerLoop.confirm_recovery(operator)` from any thread.

Reporting rule: the robot keeps reporting PROTECTIVE_STOP until it is unlocked, but a report while the
machine is already past its wait step would restart the recovery; so a report is passed on only on the
robot's rising edge (a new stop) or when the machine does not know of any stop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


@dataclass
class RecoveryHooks:
    notify: Callable[[str], None] | None = None
    confirm: Callable[[], str | None] | None = None


class RecoveryDriver:
    def __init__(self, safety, arm, hooks: RecoveryHooks | None, emit):
        self.safety, self.arm, self.hooks, self.emit = safety, arm, hooks or RecoveryHooks(), emit
        self._arm_was_stopped = False
        self._now = 0.0

    def update(self, now: float, arm_stopped: bool) -> None:
        stops = self.safety.stops
        self._now = now
        if arm_stopped and (not self._arm_was_stopped or not stops.protective):
            self.safety.report_protective_stop(now)
        self._arm_was_stopped = arm_stopped
        if not stops.protective:
            return
        action = stops.update(now)
        if action == "notify_operator":
            self._call("notify", "robot protective stop: the controller holds; recovery after the unlock delay")
            stops.notified(now)
        elif action == "unlock_protective_stop":
            try:
                ok = bool(self.arm.unlock_protective_stop())
            except Exception as exc:  # a driver error must not kill the loop
                self.emit("driver_error", now, f"unlock_protective_stop failed: {exc!r}", "error")
                ok = False
            if ok:
                self._arm_was_stopped = False
                stops.unlocked(now)
        elif action == "rearm":  # the loop holds at the measured joints until motion is allowed again
            stops.rearmed(now)
        elif action == "await_operator_confirmation" and self.hooks.confirm is not None:
            operator = self._call("confirm")
            if isinstance(operator, str) and operator.strip():
                stops.confirm(now, operator)

    def _call(self, name: str, *args):
        fn = getattr(self.hooks, name)
        if fn is None:
            return None
        try:
            return fn(*args)
        except Exception as exc:
            self.emit("hook_error", self._now, f"recovery hook {name} raised {exc!r}", "warning")
            return None


__all__ = ["RecoveryHooks", "RecoveryDriver"]
