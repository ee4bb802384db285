"""Trajectory pieces of the controller: the spline is C2 through its knots, blends and stops are smooth."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from runtime.controller.interpolate import Blend, Hold, Spline, StopCurve, smoothstep, stop_duration


def _finite_diff(traj, t0, t1, dt=1e-4):
    ts = np.arange(t0, t1, dt)
    p = np.array([traj.eval(t)[0] for t in ts])
    return ts, p, np.diff(p, axis=0) / dt


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=2, max_size=12), st.floats(-0.5, 0.5))
def test_spline_interpolates_knots_and_is_c2(values, v0):
    n = len(values)
    times = 10.0 + 0.1 * np.arange(n)
    knots = np.outer(values, np.linspace(0.5, 1.0, 6))
    s = Spline(times, knots, v_start=np.full(6, v0))
    for t, q in zip(times, knots):
        assert np.allclose(s.eval(t)[0], q, atol=1e-9)
    assert np.allclose(s.eval(times[0] + 1e-12)[1], v0, atol=1e-6)
    assert np.allclose(s.eval(times[-1] - 1e-12)[1], 0.0, atol=1e-6)  # ends at rest
    eps = 1e-9
    for t in times[1:-1]:  # velocity and acceleration continuous across interior knots
        a, b = s.eval(t - eps), s.eval(t + eps)
        assert np.allclose(a[1], b[1], atol=1e-5)
        assert np.allclose(a[2], b[2], atol=1e-4)
    # analytic derivatives agree with finite differences
    t = times[0] + 0.037
    h = 1e-6
    assert np.allclose((s.eval(t + h)[0] - s.eval(t - h)[0]) / (2 * h), s.eval(t)[1], atol=1e-4)
    assert np.allclose((s.eval(t + h)[1] - s.eval(t - h)[1]) / (2 * h), s.eval(t)[2], atol=1e-3)


def test_smoothstep_ends_flat():
    assert smoothstep(0.0) == (0.0, 0.0, 0.0) and smoothstep(1.0) == (1.0, 0.0, 0.0)
    w, w1, w2 = smoothstep(0.5)
    assert abs(w - 0.5) < 1e-12 and abs(w1 - 1.875) < 1e-12 and abs(w2) < 1e-12


def test_blend_is_continuous_and_ends_on_the_new_trajectory():
    old = Spline([0.0, 1.0, 2.0], np.outer([0.0, 0.3, 0.6], np.ones(6)), v_start=np.full(6, 0.3))
    new = Spline([0.4, 1.0, 2.0], np.outer([0.15, 0.33, 0.62], np.ones(6)), v_start=np.full(6, 0.3))
    b = Blend(old, new, 0.5, 0.2)
    assert np.allclose(b.eval(0.5)[0], old.eval(0.5)[0]) and np.allclose(b.eval(0.7)[0], new.eval(0.7)[0])
    ts, p, v = _finite_diff(b, 0.3, 0.9)
    a = np.diff(v, axis=0) / 1e-4
    assert np.max(np.abs(np.diff(p, axis=0))) < 1e-4  # no jump
    assert np.max(np.abs(np.diff(a, axis=0))) < 0.1  # acceleration continuous (C2) at the blend ends
    assert b.settled(0.8) is new and b.settled(0.6) is b


def test_stop_curve_comes_to_rest_within_limits():
    v0, a0 = np.array([0.8, -0.5, 0.3, 1.2, 0.0, 0.1]), np.array([1.0, 0.0, -2.0, 0.0, 0.0, 0.0])
    acc, jerk = np.array([5, 5, 5, 10, 10, 10.0]), np.array([150, 150, 150, 300, 300, 300.0])
    T = stop_duration(v0, a0, np.ones(6), acc, jerk, budget=0.5)
    c = StopCurve(1.0, np.zeros(6), v0, a0, T)
    p, v, a = c.eval(1.0)
    assert np.allclose(v, v0) and np.allclose(a, a0)
    p, v, a = c.eval(1.0 + T)
    assert np.allclose(v, 0.0) and np.allclose(a, 0.0)
    ts = np.linspace(1.0, 1.0 + T, 400)
    A = np.array([c.eval(t)[2] for t in ts])
    assert np.all(np.abs(A) <= acc * 0.5 * 1.05 + np.abs(a0))
    assert isinstance(c.settled(1.0 + T), Hold)
