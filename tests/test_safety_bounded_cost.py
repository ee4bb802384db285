"""Bounded per-cycle cost: the IK fallback (stop policy instead of a full solver) and the shortcuts behind it.

When the bounded Newton IK finds no joint target (a projected target far from the desired joints, a far TCP
target), the filter follows its stop policy for the cycle with an `ik_fallback` event, and never runs the
analytic IK. A target sliding along the workspace boundary keeps being solved by the warm start (last cycle's
solution). The shortcuts that keep the worst case bounded (joints far from their limits skip the position
check; the braking check's per-cycle gradient cache) give exactly the results of the full computation.
"""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safety.filter import BRAKING, HOLDING, TRACK, SafetyFilter
from safety.harness import Command, check_stream, run_stream
from safety.limits import default_limits, load_limits
from safety.shaping import IK_BUDGET

warnings.simplefilter("ignore", UserWarning)

N = max(25, int(os.environ.get("SUDD_SAFETY_EXAMPLES", "200")) // 4)
PROPS = settings(max_examples=N, deadline=None, suppress_health_check=[HealthCheck.too_slow])
HOME = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
KEEPOUT = (0.05, 0.30, 0.0, 0.30, 0.55, 0.20)
LIMITS = {"ur5e": default_limits("ur5e"), "ur5": default_limits("ur5"),
          "keepout": load_limits(None, "ur5e", {"workspace.keepout": [list(KEEPOUT)],
                                                "workspace.box_min": [-0.6, 0.05, 0.0],
                                                "workspace.box_max": [0.6, 0.8, 0.7]})}


@pytest.fixture
def no_full_ik(monkeypatch):
    """The analytic IK must never run inside a filter cycle."""
    from sim.kinematics import Kinematics

    def refuse(*args, **kw):
        raise AssertionError("the safety filter ran the full IK solver")

    monkeypatch.setattr(Kinematics, "ik", refuse)


def _recording(filt):
    """Record the kinds reported to the filter's events, per cycle (reset by the caller)."""
    seen = []
    report = filt.events.report

    def rec(kind, now, *args, **kw):
        seen.append(kind)
        return report(kind, now, *args, **kw)

    filt.events.report = rec
    return seen


def _stop_policy_velocity(filt):
    q, v, a = (x.tolist() for x in filt.commanded)
    out = [0.0] * 6
    filt.limiter.stop_velocity(v, a, out)
    return np.array(out)


def _tcp_target(filt, q, dp):
    px, py, pz, R = filt.fk.pose(list(q))
    T = np.eye(4)
    T[:3, :3] = np.reshape(R, (3, 3))
    T[:3, 3] = np.array((px, py, pz)) + dp
    return T


# ---- the fallback ---------------------------------------------------------------------------------------------
def test_unreachable_projection_brakes_with_the_stop_policy(no_full_ik):
    """A joint target deep below the table whose projection Newton cannot reach from the desired joints: the
    moving arm decelerates exactly as the stop policy says, comes to rest, holds, and resumes on a reachable
    target."""
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    dt = filt.dt
    seen = _recording(filt)
    q = HOME
    qs = [HOME]
    for k in range(40):  # get moving
        q = filt.step(HOME + 0.2, q, None, k * dt, k * dt).q
        qs.append(q)
    dive = HOME.copy()
    dive[1] += 1.2  # shoulder down through the table: the projection is ~0.5 rad away from these joints
    expect = _stop_policy_velocity(filt)
    assert np.abs(expect).max() > 0.01  # really moving
    seen.clear()
    r = filt.step(dive, q, None, 40 * dt, 40 * dt)
    assert "ik_fallback" in seen and r.mode == BRAKING
    assert any(e.kind == "ik_fallback" for e in r.events)
    np.testing.assert_allclose(r.qd, expect, rtol=0, atol=1e-9)
    qs.append(r.q)
    modes = []
    for k in range(41, 400):
        expect = _stop_policy_velocity(filt)
        r = filt.step(dive, r.q, None, k * dt, k * dt)
        np.testing.assert_allclose(r.qd, expect, rtol=0, atol=1e-9)
        modes.append(r.mode)
        qs.append(r.q)
    assert set(modes) <= {BRAKING, HOLDING} and modes[-1] == HOLDING
    assert not check_stream(np.array(qs), dt, filt.limits, filt.fk, filt.workspace)
    for k in range(400, 420):  # a reachable command is followed again
        r = filt.step(HOME + 0.05, r.q, None, k * dt, k * dt)
    assert r.mode not in (BRAKING, HOLDING)


def test_far_tcp_target_holds_and_a_near_one_is_followed(no_full_ik):
    """A TCP target 30 cm away is not solved (Newton's first step exceeds its bound): held, with the event."""
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    far = _tcp_target(filt, HOME, (0.3, 0.0, 0.0))
    res = run_stream(filt, HOME, [Command(q=None, tcp=far, command_time=k * filt.dt) for k in range(50)])
    assert set(res.modes) == {HOLDING} and np.array_equal(res.q[-1], HOME)
    assert [e.kind for e in res.events if e.end is None] == ["ik_fallback"]
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    near = _tcp_target(filt, HOME, (0.05, 0.0, 0.0))
    res = run_stream(filt, HOME, [Command(q=None, tcp=near, command_time=k * filt.dt) for k in range(1000)])
    assert not any(e.kind == "ik_fallback" for e in res.events)
    np.testing.assert_allclose(filt.fk.pose(list(res.q[-1]))[:3], near[:3, 3], atol=1e-6)


def _slide(filt, depth, speed=0.1):
    """Joint commands along a TCP path from HOME down to `depth` below the table, then 25 cm along x."""
    px, py, pz, R = filt.fk.pose(list(HOME))
    p, q, out = np.array([px, py, pz]), HOME.copy(), []
    for w in ((px, py, depth), (px + 0.25, py, depth)):
        w = np.asarray(w)
        n = max(1, int(np.linalg.norm(w - p) / speed / filt.dt))
        for s in np.linspace(0, 1, n + 1)[1:]:
            q = np.array(filt.fk.solve(tuple(p + s * (w - p)), R, q))
            out.append(q)
        p = w
    return out, px


def test_warm_start_keeps_a_deep_target_sliding_along_the_table(no_full_ik):
    """Desired joints 20 cm below the table: their projection is too far from them for Newton's branch check,
    but each cycle's solution continues the last one's, so the arm slides along the table all the way; the
    same pose commanded at once (no solution to continue) falls back and holds."""
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    qs, px = _slide(filt, -0.2)
    res = run_stream(filt, HOME, [Command(q=q, command_time=k * filt.dt) for k, q in enumerate(qs + qs[-1:] * 300)])
    assert not any(e.kind == "ik_fallback" for e in res.events)
    assert not check_stream(res.q, filt.dt, filt.limits, filt.fk, filt.workspace)
    assert abs(filt.fk.pose(list(res.q[-1]))[0] - (px + 0.25)) < 1e-6
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    res = run_stream(filt, HOME, [Command(q=qs[-1], command_time=k * filt.dt) for k in range(300)])
    assert any(e.kind == "ik_fallback" for e in res.events) and set(res.modes) == {HOLDING}


# ---- bounded cost on hostile streams --------------------------------------------------------------------------
KINDS = ("dive", "random", "tcp_far", "tcp_near", "keepout", "jump", "smooth")


def _hostile(filt, seed, segs):
    rng = np.random.default_rng(seed)
    out, tgt = [], HOME.copy()
    for kind, n, x in segs:
        for k in range(n):
            q, tcp = tgt, None
            if kind == "dive":
                q = HOME.copy()
                q[1] += rng.uniform(0.2, 1.4) * x
            elif kind == "random":
                q = HOME + rng.normal(0.0, 0.6 * x, 6)
            elif kind in ("tcp_far", "tcp_near"):
                q, tcp = None, _tcp_target(filt, HOME, rng.normal(0.0, (0.4 if kind == "tcp_far" else 0.03) * x, 3))
            elif kind == "keepout":
                p = (rng.uniform(KEEPOUT[0], KEEPOUT[3]), rng.uniform(KEEPOUT[1], KEEPOUT[4]), rng.uniform(0.0, 0.2))
                q, tcp = None, _tcp_target(filt, HOME, np.array(p) - filt.fk.pose(list(HOME))[:3])
            elif kind == "jump":
                if k == 0:
                    tgt = HOME + rng.uniform(-3.0, 3.0, 6) * x
                q = tgt
            else:
                q = HOME + 0.3 * x * np.sin(np.arange(6) + 4.0 * k * filt.dt)
            out.append((q, tcp))
    return out


@PROPS
@given(st.sampled_from(sorted(LIMITS)), st.integers(0, 2**32 - 1),
       st.lists(st.tuples(st.sampled_from(KINDS), st.integers(1, 60), st.floats(0.05, 1.0)), min_size=1, max_size=4))
def test_hostile_streams_stay_within_the_ik_budget_and_fall_back_safely(name, seed, segs):
    from sim.kinematics import Kinematics

    filt = SafetyFilter(LIMITS[name], collision=False)
    fk = filt.fk
    solve = fk.solve
    spent = [0]

    def counted(*args, **kw):
        sol = solve(*args, **kw)
        spent[0] += fk.iterations
        return sol

    fk.solve = counted
    seen = _recording(filt)
    dt = filt.dt
    q = HOME
    qs = [HOME]
    ik = Kinematics.ik
    try:
        Kinematics.ik = None  # calling it would raise
        for k, (cmd, tcp) in enumerate(_hostile(filt, seed, segs)):
            spent[0] = 0
            seen.clear()
            expect = _stop_policy_velocity(filt)
            r = filt.step(cmd, qs[max(0, len(qs) - 2)], None, k * dt, k * dt, desired_tcp=tcp)
            assert spent[0] <= IK_BUDGET
            if "ik_fallback" in seen:
                assert r.mode in (BRAKING, HOLDING)
                np.testing.assert_allclose(r.qd, expect, rtol=0, atol=1e-9)
            qs.append(r.q)
    finally:
        Kinematics.ik = ik
    assert not check_stream(np.array(qs), dt, filt.limits, filt.fk, filt.workspace)


def test_a_safe_stream_does_no_ik_at_all():
    filt = SafetyFilter(LIMITS["ur5e"], collision=False)
    calls = []
    solve = filt.fk.solve
    filt.fk.solve = lambda *a, **kw: calls.append(1) or solve(*a, **kw)
    t = np.arange(1, 501) * filt.dt
    Q = HOME + ((1 - np.cos(2 * np.pi * 0.5 * t)) ** 2 / 4)[:, None] * 0.05
    res = run_stream(filt, HOME, [Command(q=q, command_time=k * filt.dt) for k, q in enumerate(Q)])
    assert set(res.modes) == {TRACK} and not calls


# ---- the shortcuts give the full computation's results ------------------------------------------------------
@pytest.mark.parametrize("variant", ["ur5e", "ur5"])
def test_joints_far_from_their_limits_are_position_feasible_over_their_whole_box(variant):
    filt = SafetyFilter(LIMITS[variant], collision=False)
    lim = filt.limiter
    rng = np.random.default_rng(3)
    far_seen = near_seen = 0
    for _ in range(3000):
        q = rng.uniform(lim.L, lim.U).tolist()
        v = (rng.uniform(-1.0, 1.0, 6) * lim.V).tolist()
        a = (rng.uniform(-1.0, 1.0, 6) * lim.A).tolist()
        lim.box(v, a)
        far = lim._far(q, v)
        for i in range(6):
            if not far[i]:
                near_seen += 1
                continue
            far_seen += 1
            for x in np.linspace(lim.lo[i], lim.hi[i], 9):
                assert lim.position_ok(i, q[i], v[i], float(x)), (i, q[i], v[i], x)
    assert far_seen > 1000 and near_seen > 100


def test_braking_check_gradient_cache_matches_a_fresh_evaluation():
    """Reusing the frames/points objects (the cache) gives the same verdict as fresh copies (no cache hit)."""
    for name in ("ur5e", "keepout"):
        filt = SafetyFilter(LIMITS[name], collision=False)
        ws, fk, lim = filt.workspace, filt.fk, filt.limiter
        rng = np.random.default_rng(4)
        verdicts = set()
        for _ in range(200):
            px, py, pz, R = fk.pose(list(HOME))
            T = np.eye(4)
            T[:3, :3] = np.reshape(R, (3, 3))
            T[:3, 3] = (rng.uniform(-0.5, 0.5), rng.uniform(0.1, 0.7), rng.uniform(0.02, 0.3))
            q = fk.solve(tuple(T[:3, 3]), R, HOME.tolist(), iters=20, max_dev=math.inf)
            if q is None:
                continue
            fr = fk.frames(q)
            pose = fk.pose(q)
            pts, _ = ws.at(pose)
            cons = ws.constraints(pts)
            for _ in range(10):
                hi = np.abs(rng.normal(0.0, 0.05, 6))
                lo = -np.abs(rng.normal(0.0, 0.05, 6))
                cached = ws.braking_ok(fr, pts, cons, lo.tolist(), hi.tolist())
                fresh = ws.braking_ok(lambda: fk.frames(list(q)), [tuple(p) for p in pts], cons, lo.tolist(),
                                      hi.tolist())
                assert cached == fresh
                verdicts.add(cached)
        assert verdicts == {True, False}
