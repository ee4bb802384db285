"""safety.stop_states and safety.watchdog: e-stop latch, protective-stop recovery, command freshness."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from safety.events import EventCoalescer
from safety.stop_states import CONFIRM, ESTOP, NOTIFY, PROTECTIVE_STOP, REARM, RUNNING, UNLOCK, WAIT, StopStateMachine
from safety.watchdog import FRESH, FUTURE, INVALID, OUT_OF_ORDER, STALE, CommandWatchdog

ACTIONS = ("estop", "reset", "reset_anon", "protective", "notified", "unlocked", "rearmed", "confirm", "tick")


def _apply(m, action, now):
    if action == "estop":
        m.estop(now)
    elif action == "reset":
        return m.reset_estop(now, "op")
    elif action == "reset_anon":
        return m.reset_estop(now, "  ")
    elif action == "protective":
        m.robot_protective_stop(now)
    elif action == "notified":
        return m.notified(now)
    elif action == "unlocked":
        return m.unlocked(now)
    elif action == "rearmed":
        return m.rearmed(now)
    elif action == "confirm":
        return m.confirm(now, "op")
    else:
        m.update(now)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(ACTIONS), st.floats(0.0, 3.0)), max_size=40))
def test_estop_latches_until_an_operator_resets_and_nothing_raises(steps):
    m = StopStateMachine(events=EventCoalescer())
    now = 0.0
    latched = False
    for action, dt in steps:
        now += dt
        _apply(m, action, now)  # never raises, whatever the order
        if action == "estop":
            latched = True
        elif action == "reset" and latched:
            latched = False
        assert (m.state == ESTOP) == latched
        assert not (latched and m.allows_motion)
        assert m.state in (RUNNING, ESTOP, PROTECTIVE_STOP)


def test_protective_stop_recovery_sequence():
    ev = EventCoalescer()
    m = StopStateMachine(protective_wait=5.0, events=ev)
    m.robot_protective_stop(10.0)
    assert m.state == PROTECTIVE_STOP and m.step == NOTIFY and m.action == "notify_operator"
    assert not m.unlocked(10.1) and not m.confirm(10.1, "op")  # out of order: refused
    assert m.notified(10.2) and m.step == WAIT and m.update(14.9) is None
    assert m.update(15.0) == "unlock_protective_stop" and m.step == UNLOCK
    assert m.unlocked(15.1) and m.step == REARM and m.action == "rearm"
    assert m.rearmed(15.2) and m.step == CONFIRM and m.action == "await_operator_confirmation"
    assert not m.confirm(15.3, "")  # needs an operator id
    assert m.confirm(15.4, "alice") and m.state == RUNNING and m.allows_motion and m.resumed
    kinds = [e.kind for e in ev.flush(16.0)]
    assert kinds.count("invalid_request") == 3 and "protective_stop" in kinds


def test_new_protective_stop_restarts_recovery_and_estop_overrides():
    m = StopStateMachine(protective_wait=5.0)
    m.robot_protective_stop(0.0)
    m.notified(0.1)
    m.update(5.0)
    m.unlocked(5.1)
    m.robot_protective_stop(5.2)  # stopped again during recovery
    assert m.step == NOTIFY and m.stopped_at == 5.2
    m.estop(5.3)
    assert m.state == ESTOP and m.action == "await_estop_reset"
    assert m.reset_estop(5.4, "bob") and m.state == PROTECTIVE_STOP and not m.resumed


def test_watchdog_freshness():
    w = CommandWatchdog(max_age=0.1, max_future=0.05)
    assert w.check(1.0, 0.95) == FRESH
    assert w.check(1.02, 0.95) == FRESH  # same command repeated: still fresh while young
    assert w.check(1.06, 0.95) == STALE
    assert w.check(1.07, 0.90) == OUT_OF_ORDER  # older than one already used
    assert w.check(1.08, 1.2) == FUTURE
    assert w.check(math.nan, 1.0) == INVALID and w.check(1.0, None) == INVALID
    assert w.check(1.09, 1.08) == FRESH  # resumes on a fresh command


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 0.01), st.floats(-0.3, 0.1)), min_size=1, max_size=60))
def test_watchdog_never_accepts_old_or_out_of_order(steps):
    w = CommandWatchdog(max_age=0.1, max_future=0.05)
    now, newest = 0.0, -math.inf
    for dt, offset in steps:
        now += dt
        ct = now + offset
        status = w.check(now, ct)
        if status == FRESH:
            assert now - ct <= 0.1 and ct - now <= 0.05 and ct >= newest
            newest = ct
        else:
            assert now - ct > 0.1 or ct - now > 0.05 or ct < newest
