"""safety.filter: when it stops and holds, and what lets it move again — stale, late, future and malformed
commands, the e-stop latch, a tracking error, a protective stop. Streams and set-up: safety_filter_streams.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st
from safety_filter_streams import HOME, SIDE, commands, inside, make_filter, start_pose, streams

from safety.filter import BRAKING, HOLDING
from safety.harness import Command, check_stream, run_stream, stop_within


# ---- stale commands: stop within the braking distance, hold, resume only on fresh commands -----------------
@SIDE
@given(st.sampled_from(("ur5e", "ur5")), st.integers(0, 2**32 - 1), st.integers(5, 400), st.booleans())
def test_stale_command_stops_within_braking_distance_and_holds(name, seed, moving, jumpy):
    filt = make_filter(name)
    rng = np.random.default_rng(seed)
    dt, max_age = filt.dt, filt.limits.command.max_age
    q0 = HOME
    tgt = q0 + rng.uniform(-1.0, 1.0, 6) * (1.0 if jumpy else 0.2)
    cmds = [Command(q=tgt, command_time=k * dt) for k in range(moving)]
    # then no new command arrives: the last one is repeated with its time stamp until it is too old
    frozen = (moving - 1) * dt
    stale_from = next(k for k in range(moving, 10**6) if k * dt - frozen > max_age)
    n_stop = int(math.ceil(2.0 / dt))
    cmds += [Command(q=tgt, command_time=frozen) for _ in range(stale_from - moving)]
    cmds += [Command(q=tgt + rng.normal(0, 0.3, 6), command_time=frozen) for _ in range(n_stop)]
    res = run_stream(filt, q0, cmds)
    assert not check_stream(res.q, dt, filt.limits)
    # res.q[k + 1] is the output of command k: the stop starts from the state after the last fresh command
    assert not stop_within(res.q, stale_from, dt, filt.limiter)
    tail = res.modes[stale_from:]
    assert set(tail) <= {BRAKING, HOLDING} and tail[-1] == HOLDING
    assert any(e.kind == "stale_command" for e in res.events)
    # a late command never resumes motion; a fresh one does
    before = res.q[-1].copy()
    r = filt.step(tgt, before, None, len(cmds) * dt, frozen + dt)
    assert np.array_equal(r.q, before) and r.mode == HOLDING
    moved = False
    for k in range(len(cmds) + 1, len(cmds) + 200):
        r = filt.step(q0, r.q, None, k * dt, k * dt)
        moved = moved or not np.array_equal(r.q, before)
    assert moved or np.allclose(before, q0, atol=1e-9)


# ---- e-stop latches ---------------------------------------------------------------------------------------
@SIDE
@given(streams(max_segments=3, max_len=80), st.integers(0, 150))
def test_estop_latches_across_any_later_input(case, at):
    name, start, seed, segs = case
    filt = make_filter(name)
    q0 = start_pose(name, start)
    assume(inside(filt, q0))
    dt = filt.dt
    lead = [Command(q=q0 + 0.3 * np.sin(np.arange(6) + k * dt), command_time=k * dt) for k in range(at)]
    later = commands(filt, q0, seed, segs, filt.limits.command.max_age)
    for c in later:  # shift to follow the lead-in; keep their freshness pattern
        c.command_time += at * dt
    later += [Command(q=q0 + 0.5, command_time=(at + len(later) + k) * dt) for k in range(int(1.0 / dt))]
    if later:
        later[0].estop = True
    res = run_stream(filt, q0, lead + later)
    assert not check_stream(res.q, dt, filt.limits, filt.fk, filt.workspace)
    assert all(s == "estop" for s in res.states[at:])
    assert not stop_within(res.q, at, dt, filt.limiter)  # stopped at the maximum safe rate, then held
    assert res.modes[-1] == HOLDING
    assert filt.reset_estop(len(res.states) * dt, "operator A")
    r = filt.step(q0 + 0.5, res.q[-1], None, (len(res.states) + 1) * dt, (len(res.states) + 1) * dt)
    assert r.state == "running"


def test_estop_reset_needs_an_operator():
    filt = make_filter("ur5e")
    filt.step(HOME, HOME, None, 0.0, 0.0)
    filt.estop(0.01)
    assert not filt.reset_estop(0.02, "")
    assert filt.stops.state == "estop"
    r = filt.step(HOME + 0.1, HOME, None, 0.03, 0.03)
    assert r.state == "estop" and r.mode in (BRAKING, HOLDING)


# ---- malformed input holds, with an event -------------------------------------------------------------------
@pytest.mark.parametrize("bad", [
    [np.nan] * 6, [0.0, 0.0, np.inf, 0.0, 0.0, 0.0], [0.0] * 5, [[0.0] * 6], "abc", np.zeros(7),
    np.array([1 + 1j] * 6), {"q": 1},
])
def test_malformed_joint_command_holds_with_event(bad):
    filt = make_filter("ur5e")
    for k in range(20):  # get moving first
        r = filt.step(HOME + 0.001 * k, HOME, None, k * filt.dt, k * filt.dt)
    q, v, a = (x.tolist() for x in filt.commanded)
    expect = [0.0] * 6
    filt.limiter.stop_velocity(v, a, expect)  # the stop policy's next velocity from this state
    r = filt.step(bad, r.q, None, 20 * filt.dt, 20 * filt.dt)
    assert r.mode in (BRAKING, HOLDING)
    assert any(e.kind == "malformed_command" for e in r.events)
    np.testing.assert_allclose(r.qd, expect, rtol=0, atol=1e-9)


@pytest.mark.parametrize("tcp", [
    np.diag([1.1, 1.0, 1.0, 1.0]),  # not a rotation
    np.array([[1, 0, 0, 0.1], [0, 1, 0, 0.4], [0, 0, -1, 0.3], [0, 0, 0, 1.0]]),  # reflection (det -1)
    np.array([0.1, 0.4, 0.3, 0.9, 0.0, 0.0, 0.0]),  # quaternion of norm 0.9
    np.array([0.1, 0.4, np.nan, 0.0, 0.0, 0.0]),
    np.eye(3),
])
def test_malformed_tcp_target_holds(tcp):
    filt = make_filter("ur5e")
    r = filt.step(None, HOME, None, 0.0, 0.0, desired_tcp=tcp)
    assert r.mode == HOLDING and np.array_equal(r.q, HOME)
    assert any(e.kind == "malformed_command" for e in r.events)


def test_out_of_order_and_future_commands_are_not_followed():
    filt = make_filter("ur5e")
    dt = filt.dt
    q = HOME
    for k in range(10):
        q = filt.step(HOME, q, None, k * dt, k * dt).q
    r = filt.step(HOME + 0.5, q, None, 10 * dt, 5 * dt)  # older than the last command used
    assert r.mode == HOLDING and any(e.kind == "out_of_order_command" for e in r.events)
    r = filt.step(HOME + 0.5, r.q, None, 11 * dt, 11 * dt + 1.0)  # a second in the future
    assert r.mode == HOLDING and any(e.kind == "future_command" for e in r.events)
    r = filt.step(HOME + 0.5, r.q, None, 12 * dt, 12 * dt)
    assert r.mode != HOLDING


def test_first_measurement_must_be_valid():
    filt = make_filter("ur5e")
    with pytest.raises(ValueError, match="first measured joint state"):
        filt.step(HOME, [np.nan] * 6, None, 0.0, 0.0)


# ---- tracking error and protective stop -------------------------------------------------------------------
def test_tracking_error_stops_and_recovers():
    filt = make_filter("ur5e")
    dt = filt.dt
    q = HOME
    for k in range(50):
        q = filt.step(HOME + 0.3, q, None, k * dt, k * dt).q
    r = filt.step(HOME + 0.3, q + 0.5, None, 50 * dt, 50 * dt)  # the arm is not where it was sent
    assert r.mode in (BRAKING, HOLDING) and any(e.kind == "tracking_error" for e in r.events)
    q = r.q
    for k in range(51, 800):
        r = filt.step(HOME + 0.3, q, None, k * dt, k * dt)  # measured follows again
        q = r.q
    assert r.mode != HOLDING or np.allclose(q, HOME + 0.3)


def test_protective_stop_holds_then_resyncs_after_recovery():
    filt = make_filter("ur5e")
    dt = filt.dt
    q = HOME
    for k in range(100):
        q = filt.step(HOME + 0.2, q, None, k * dt, k * dt).q
    filt.report_protective_stop(100 * dt)
    k = 101
    for _ in range(400):
        r = filt.step(HOME + 0.2, q, None, k * dt, k * dt)
        q = r.q
        k += 1
    assert r.state == "protective_stop" and r.mode == HOLDING
    st_ = filt.stops
    assert st_.notified(k * dt) and not st_.unlocked(k * dt)  # too early: the controller's 5 s
    st_.update(100 * dt + 5.0)
    assert st_.unlocked(100 * dt + 5.0) and st_.rearmed(100 * dt + 5.1) and st_.confirm(100 * dt + 5.2, "op")
    measured = q + 0.001  # the controller stopped the arm a little elsewhere
    r = filt.step(HOME + 0.2, measured, None, 100 * dt + 5.3, 100 * dt + 5.3)
    assert r.resynced and r.state == "running"
