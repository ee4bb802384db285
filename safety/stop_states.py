"""E-stop latch and protective-stop recovery, as a pure state machine (the clock is passed in).

States:

* RUNNING: motion allowed.
* ESTOP: latched by `estop()`. The filter decelerates at the maximum safe rate and holds. Only
  `reset_estop(now, operator)` with a non-empty operator id leaves it; nothing else does (no command,
  no timeout, no robot report).
* PROTECTIVE_STOP: the robot reported a protective stop. Recovery walks through steps, each started by
  the runtime reporting what it did, and the machine says what to do next (`action`):

      NOTIFY   -> action "notify_operator";      runtime calls notified(now)
      WAIT     -> until protective_wait (5 s) after the stop; no action (the controller refuses earlier)
      UNLOCK   -> action "unlock_protective_stop"; runtime calls unlocked(now) once the robot reports it clear
      REARM    -> action "rearm";                 runtime re-arms servoing / its watchdog, calls rearmed(now)
      CONFIRM  -> action "await_operator_confirmation"; operator calls confirm(now, operator) -> RUNNING

  A new protective stop during recovery restarts it. An e-stop overrides everything; after its reset a
  protective stop that is still pending resumes its recovery.

Nothing here raises on a wrong request: it is refused (returns False) and recorded as an event.
"""

from __future__ import annotations

RUNNING, ESTOP, PROTECTIVE_STOP = "running", "estop", "protective_stop"
NOTIFY, WAIT, UNLOCK, REARM, CONFIRM = "notify", "wait", "unlock", "rearm", "confirm"
_ACTIONS = {NOTIFY: "notify_operator", WAIT: None, UNLOCK: "unlock_protective_stop", REARM: "rearm",
            CONFIRM: "await_operator_confirmation"}


class StopStateMachine:
    def __init__(self, protective_wait: float = 5.0, events=None):
        self.protective_wait = float(protective_wait)
        self.events = events  # an EventCoalescer (its `instant` is used) or None
        self.estopped = False
        self.estop_reason = ""
        self.protective = False
        self.step: str | None = None
        self.stopped_at: float | None = None
        self.resumed = False  # set when motion becomes allowed again; the filter re-syncs and clears it

    # ---- queries --------------------------------------------------------------------------------------
    @property
    def state(self) -> str:
        if self.estopped:
            return ESTOP
        if self.protective:
            return PROTECTIVE_STOP
        return RUNNING

    @property
    def allows_motion(self) -> bool:
        return not self.estopped and not self.protective

    @property
    def action(self) -> str | None:
        """What the runtime should do now (None: nothing, or wait)."""
        if self.estopped:
            return "await_estop_reset"
        if self.protective:
            return _ACTIONS[self.step]
        return None

    def _event(self, kind, now, message, severity=None):
        if self.events is not None:
            self.events.instant(kind, now, message=message, severity=severity)

    def _refuse(self, now, what: str) -> bool:
        self._event("invalid_request", now, f"{what} refused in state {self.state}"
                    + (f"/{self.step}" if self.protective else ""))
        return False

    # ---- e-stop ---------------------------------------------------------------------------------------
    def estop(self, now: float, reason: str = "software e-stop") -> None:
        if not self.estopped:
            self.estopped = True
            self.estop_reason = reason
            self._event("estop", now, f"e-stop: {reason}")

    def reset_estop(self, now: float, operator: str) -> bool:
        if not self.estopped:
            return self._refuse(now, "e-stop reset")
        if not isinstance(operator, str) or not operator.strip():
            return self._refuse(now, "e-stop reset without an operator id")
        self.estopped = False
        self._event("recovery", now, f"e-stop reset by {operator.strip()}")
        if not self.protective:
            self.resumed = True
        return True

    # ---- protective stop ------------------------------------------------------------------------------
    def robot_protective_stop(self, now: float) -> None:
        """The robot reports a protective stop (call on every report; repeated reports are harmless)."""
        if self.protective and self.step in (NOTIFY, WAIT):
            return
        self.protective = True
        self.step = NOTIFY
        self.stopped_at = now
        self._event("protective_stop", now, "robot protective stop; recovery: notify, wait, unlock, re-arm, "
                                            "operator confirmation")

    def update(self, now: float) -> str | None:
        """Advance time-driven steps (WAIT -> UNLOCK); returns the current action."""
        if self.protective and self.step == WAIT and now - self.stopped_at >= self.protective_wait:
            self.step = UNLOCK
            self._event("recovery", now, "protective stop: wait over, unlock now")
        return self.action

    def notified(self, now: float) -> bool:
        if not (self.protective and self.step == NOTIFY):
            return self._refuse(now, "notified")
        self.step = WAIT
        self.update(now)
        return True

    def unlocked(self, now: float) -> bool:
        if not (self.protective and self.step == UNLOCK):
            return self._refuse(now, "unlocked")
        self.step = REARM
        self._event("recovery", now, "protective stop unlocked; re-arm")
        return True

    def rearmed(self, now: float) -> bool:
        if not (self.protective and self.step == REARM):
            return self._refuse(now, "rearmed")
        self.step = CONFIRM
        self._event("recovery", now, "re-armed; waiting for operator confirmation")
        return True

    def confirm(self, now: float, operator: str) -> bool:
        if not (self.protective and self.step == CONFIRM):
            return self._refuse(now, "confirm")
        if not isinstance(operator, str) or not operator.strip():
            return self._refuse(now, "confirm without an operator id")
        self.protective = False
        self.step = None
        self._event("recovery", now, f"protective stop recovered, confirmed by {operator.strip()}")
        if not self.estopped:
            self.resumed = True
        return True


__all__ = ["StopStateMachine", "RUNNING", "ESTOP", "PROTECTIVE_STOP", "NOTIFY", "WAIT", "UNLOCK", "REARM",
           "CONFIRM"]
