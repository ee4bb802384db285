"""safety.joint_limits: the stop policy's travel bound and the limiter's invariants under arbitrary requests.

These drive the JointLimiter directly with arbitrary velocity requests (no target shaping in front), so the
position-braking backstop and the velocity viability are exercised at their edges.
Tolerance: as safety.harness (1e-9 relative + the round-off floor of finite differences).
"""

from __future__ import annotations

import os

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from safety.harness import check_stream
from safety.joint_limits import PASS, STOP, JointLimiter
from safety.limits import default_limits

N = int(os.environ.get("SUDD_SAFETY_EXAMPLES", "200"))
PROPS = settings(max_examples=N, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _limiter(variant):
    lim = default_limits(variant)
    j = lim.joints
    from sim.robot import get_variant

    dt = get_variant(variant).control_period
    return lim, JointLimiter(j.soft_lower, j.soft_upper, j.velocity, j.acceleration, j.jerk, dt)


LIMITERS = {v: _limiter(v) for v in ("ur5e", "ur5")}


def _viable_state(L, rng):
    """A random (v, a) in the viable set: |v| <= V, |a| <= A, a within c (+-V - v)."""
    v = rng.uniform(-1, 1, 6) * np.array(L.V)
    a = np.empty(6)
    for i in range(6):
        lo = max(-L.A[i], L.c[i] * (-L.V[i] - v[i]))
        hi = min(L.A[i], L.c[i] * (L.V[i] - v[i]))
        r = rng.random()
        a[i] = lo if r < 0.25 else (hi if r < 0.5 else rng.uniform(lo, hi))
    return v, a


def _integrate(L, q, v, a, nxt):
    """Advance the commanded stream one cycle the way the filter does (finite differences of positions)."""
    dt = L.dt
    qn = [q[i] + nxt[i] * dt for i in range(6)]
    vn = [(qn[i] - q[i]) / dt for i in range(6)]
    an = [(vn[i] - v[i]) / dt for i in range(6)]
    return qn, vn, an


@PROPS
@given(st.sampled_from(sorted(LIMITERS)), st.integers(0, 2**32 - 1))
def test_stop_policy_stays_within_its_bound_and_rests(variant, seed):
    _, L = LIMITERS[variant]
    rng = np.random.default_rng(seed)
    v, a = _viable_state(L, rng)
    q = [0.0] * 6
    bp = [L.stop_bound(i, v[i], a[i]) for i in range(6)]
    bm = [L.stop_bound(i, -v[i], -a[i]) for i in range(6)]
    Q = [q]
    v, a = list(v), list(a)
    out = [0.0] * 6
    for _ in range(int(2.0 / L.dt)):
        rest = L.stop_velocity(v, a, out)
        q, v, a = _integrate(L, q, v, a, out)
        Q.append(q)
        if rest and not any(v) and not any(a):
            break
    Q = np.array(Q)
    assert not any(v) and not any(a), "not at rest within 2 s"
    assert np.all(Q.max(axis=0) <= np.array(bp) + 1e-12) and np.all(-Q.min(axis=0) <= np.array(bm) + 1e-12)


@PROPS
@given(st.sampled_from(sorted(LIMITERS)), st.integers(0, 2**32 - 1), st.integers(0, 5),
       st.sampled_from(("huge", "random", "towards", "flip")))
def test_limiter_keeps_every_limit_under_arbitrary_requests(variant, seed, joint, how):
    """Near a position limit, whatever velocity is requested, the stream keeps position/vel/acc/jerk."""
    limits, L = LIMITERS[variant]
    rng = np.random.default_rng(seed)
    q = [rng.uniform(L.L[i] + 0.5, L.U[i] - 0.5) for i in range(6)]
    side = rng.choice([-1.0, 1.0])
    q[joint] = (L.U[joint] if side > 0 else L.L[joint]) - side * rng.uniform(0.0, 0.3)
    v, a = [0.0] * 6, [0.0] * 6
    Q = [q]
    out = [0.0] * 6
    n = int(1.0 / L.dt)
    for k in range(n):
        if how == "huge":
            vt = list(rng.choice([-1, 1], 6) * 10.0 ** rng.uniform(-3, 6, 6))
        elif how == "random":
            vt = list(rng.normal(0, 2.0, 6))
        elif how == "towards":
            vt = [side * 5.0 if i == joint else rng.normal(0, 0.5) for i in range(6)]
        else:
            vt = [(1.0 if k % 2 else -1.0) * 3.0] * 6
        L.select(q, v, a, vt, out)
        q, v, a = _integrate(L, q, v, a, out)
        Q.append(q)
    assert not check_stream(np.array(Q), L.dt, limits)


@PROPS
@given(st.sampled_from(sorted(LIMITERS)), st.integers(0, 2**32 - 1))
def test_admissible_request_passes_exactly(variant, seed):
    _, L = LIMITERS[variant]
    rng = np.random.default_rng(seed)
    v, a = _viable_state(L, rng)
    q = [0.0] * 6
    L.box(list(v), list(a))
    vt = [rng.uniform(L.lo[i], L.hi[i]) for i in range(6)]
    out = [0.0] * 6
    assert L.select(q, list(v), list(a), vt, out) == PASS and out == vt


def test_hard_box_is_never_empty_on_viable_states():
    for _, L in LIMITERS.values():
        rng = np.random.default_rng(0)
        for _ in range(2000):
            v, a = _viable_state(L, rng)
            L.box(list(v), list(a))
            for i in range(6):
                assert L.lo[i] <= L.hi[i]
                # the box keeps the next state viable: |v'| <= V and a' within the anticipation bounds
                for x in (L.lo[i], L.hi[i]):
                    an = (x - v[i]) / L.dt
                    assert abs(x) <= L.V[i] + 1e-12 and abs(an) <= L.A[i] + 1e-9


def test_common_factor_keeps_direction():
    _, L = LIMITERS["ur5e"]
    q, v, a = [0.0] * 6, [0.0] * 6, [0.0] * 6
    d = np.array([1.0, -0.5, 0.25, 0.8, -1.0, 0.3])
    out = [0.0] * 6
    assert L.select(q, v, a, list(d), out) != PASS
    r = np.array(out) / d
    assert np.allclose(r, r[0], rtol=1e-12, atol=0)


def test_stop_when_no_velocity_can_avoid_the_limit():
    """Moving fast at a limit (a state the limiter would never produce itself): the stop policy."""
    _, L = LIMITERS["ur5e"]
    q = [L.U[0] - 1e-4] + [0.0] * 5
    v = [0.9] + [0.0] * 5
    a = [0.0] * 6
    out = [0.0] * 6
    assert L.select(q, v, a, [1.0] + [0.0] * 5, out) == STOP
    expect = [0.0] * 6
    L.stop_velocity(v, a, expect)
    assert out == expect
