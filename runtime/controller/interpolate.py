"""Joint trajectories evaluated at the servo rate: C2 splines through chunk knots, blends, holds, stops.

Why C2: the safety filter limits jerk on the commanded stream (150-300 rad/s^3). Linear interpolation of
10 Hz knots has an acceleration impulse at every knot, so the filter would clip every knot; a cubic spline
is continuous in position, velocity and acceleration, with a bounded (piecewise constant) jerk, so a
well-formed chunk passes the filter unchanged. The blend weight is the quintic smoothstep (zero first and
second derivative at both ends), so blending two C2 trajectories gives a C2 trajectory.

Every trajectory answers `eval(t) -> (p, v, a)` (float seconds, host monotonic clock; (6,) arrays) and
`settled(t)`, the simplest trajectory equal to it from t on (a finished blend collapses to its new part).
Objects are immutable after construction, so the loop thread can evaluate one while another thread builds
the next.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

_ZERO = np.zeros(6)
_ZERO.flags.writeable = False


class Hold:
    """Stand still at q (no chunk, or before a chunk's first knot)."""

    def __init__(self, q):
        self.q = np.array(q, dtype=float).reshape(6)
        self.end = -math.inf  # constant from this time on

    def eval(self, t: float):
        return self.q, _ZERO, _ZERO

    def settled(self, t: float):
        return self


class Spline:
    """Cubic spline through (times, knots): C2 at interior knots, start velocity `v_start`, end velocity 0.

    The start velocity defaults to the chunk's own (the slope of the parabola through the first three
    knots), so the spline is what the chunk says; matching the motion it replaces is the blend's job. The
    zero end velocity brings the arm to rest at the last knot with continuous velocity when no further chunk
    arrives (normally a new chunk replaces the tail long before). Constant outside the knots.
    """

    def __init__(self, times, knots, v_start=None):
        t = [float(x) for x in times]
        y = np.asarray(knots, dtype=float).reshape(len(t), 6)
        if len(t) > 1 and any(b <= a for a, b in zip(t, t[1:])):
            raise ValueError("spline knot times must strictly increase")
        self.times, self.knots = t, y
        self.start, self.end = t[0], t[-1]
        n = len(t)
        v = np.zeros((n, 6))
        if n > 1:
            h = np.diff(t)
            d = np.diff(y, axis=0) / h[:, None]  # secant slopes
            if v_start is not None:
                v[0] = np.asarray(v_start, dtype=float)
            elif n > 2:
                v[0] = d[0] - (d[1] - d[0]) * h[0] / (h[0] + h[1])
            else:
                v[0] = d[0]
            if n > 2:  # interior slopes from C2 continuity: a tridiagonal system (dense: n <= 256)
                m = n - 2
                A = np.zeros((m, m))
                rhs = 3.0 * (h[1:, None] * d[:-1] + h[:-1, None] * d[1:])
                for i in range(m):
                    A[i, i] = 2.0 * (h[i] + h[i + 1])
                    if i > 0:
                        A[i, i - 1] = h[i + 1]
                    if i < m - 1:
                        A[i, i + 1] = h[i]
                rhs[0] -= h[1] * v[0]
                v[1:-1] = np.linalg.solve(A, rhs)
            c2 = (3.0 * d - 2.0 * v[:-1] - v[1:]) / h[:, None]
            c3 = (v[:-1] + v[1:] - 2.0 * d) / (h * h)[:, None]
            self._c = np.stack([y[:-1], v[:-1], c2, c3], axis=1)  # (n-1, 4, 6)
        self.knot_velocities = v

    def eval(self, t: float):
        tt = self.times
        if t <= tt[0] or len(tt) == 1:
            return self.knots[0] if t <= tt[0] else self.knots[-1], _ZERO, _ZERO
        if t >= tt[-1]:
            return self.knots[-1], _ZERO, _ZERO
        i = bisect.bisect_right(tt, t) - 1
        c0, c1, c2, c3 = self._c[i]
        s = t - tt[i]
        return c0 + s * (c1 + s * (c2 + s * c3)), c1 + s * (2.0 * c2 + 3.0 * s * c3), 2.0 * c2 + 6.0 * s * c3

    def settled(self, t: float):
        return self


def smoothstep(tau: float) -> tuple[float, float, float]:
    """Quintic smoothstep w = 10 tau^3 - 15 tau^4 + 6 tau^5 and its first two derivatives in tau."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2 = tau * tau
    return t2 * tau * (10.0 + tau * (-15.0 + 6.0 * tau)), 30.0 * t2 * (1.0 - tau) ** 2, \
        60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)


# peak |w'|, |w''|, |w'''| of the smoothstep over tau in [0, 1] (per unit duration)
W1_MAX, W2_MAX, W3_MAX = 1.875, 10.0 / math.sqrt(3.0), 60.0


class Blend:
    """(1 - w) old + w new over [t0, t0 + T]: the new chunk takes over the unexecuted tail without a jump."""

    def __init__(self, old, new, t0: float, duration: float):
        self.old, self.new, self.t0, self.T = old, new, float(t0), float(duration)
        self.end = max(self.t0 + self.T, getattr(new, "end", -math.inf))

    def eval(self, t: float):
        if t >= self.t0 + self.T:
            return self.new.eval(t)
        if t <= self.t0:
            return self.old.eval(t)
        p0, v0, a0 = self.old.eval(t)
        p1, v1, a1 = self.new.eval(t)
        w, w1, w2 = smoothstep((t - self.t0) / self.T)
        w1, w2 = w1 / self.T, w2 / (self.T * self.T)
        dp, dv = p1 - p0, v1 - v0
        return p0 + w * dp, v0 + w * dv + w1 * dp, a0 + w * (a1 - a0) + 2.0 * w1 * dv + w2 * dp

    def settled(self, t: float):
        if t >= self.t0 + self.T:
            return self.new.settled(t)
        old = self.old.settled(t)
        return self if old is self.old else Blend(old, self.new, self.t0, self.T)


class StopCurve:
    """Quintic from (p0, v0, a0) at t0 to rest at t0 + T (the controlled stop's trajectory).

    The end point p0 + v0 T / 2 + a0 T^2 / 12 keeps the motion's direction and makes the velocity fall
    monotonically for a0 = 0 (it is the minimum-jerk choice of a free end point)."""

    def __init__(self, t0: float, p0, v0, a0, duration: float):
        T = float(duration)
        p0, v0, a0 = (np.asarray(x, dtype=float) for x in (p0, v0, a0))
        p1 = p0 + v0 * T / 2.0 + a0 * T * T / 12.0
        dp = p1 - p0
        c3 = (20.0 * dp - 12.0 * v0 * T - 3.0 * a0 * T * T) / (2.0 * T ** 3)
        c4 = (-30.0 * dp + 16.0 * v0 * T + 3.0 * a0 * T * T) / (2.0 * T ** 4)
        c5 = (12.0 * dp - 6.0 * v0 * T - a0 * T * T) / (2.0 * T ** 5)
        self._c = (p0, v0, a0 / 2.0, c3, c4, c5)
        self.t0, self.T, self.p1 = float(t0), T, p1
        self.end = self.t0 + T

    def eval(self, t: float):
        if t >= self.end:
            return self.p1, _ZERO, _ZERO
        s = max(0.0, t - self.t0)
        c0, c1, c2, c3, c4, c5 = self._c
        p = c0 + s * (c1 + s * (c2 + s * (c3 + s * (c4 + s * c5))))
        v = c1 + s * (2 * c2 + s * (3 * c3 + s * (4 * c4 + s * 5 * c5)))
        a = 2 * c2 + s * (6 * c3 + s * (12 * c4 + s * 20 * c5))
        return p, v, a

    def settled(self, t: float):
        return Hold(self.p1) if t >= self.end else self


def stop_duration(v0, a0, vel, acc, jerk, budget: float = 0.5, minimum: float = 0.02) -> float:
    """Shortest StopCurve duration whose peak acceleration and jerk stay within `budget` of the limits.

    Bounds of the quintic (a0 = 0): peak |a| = 1.5 |v0| / T, peak |j| = 6 |v0| / T^2; a0 adds its own
    terms (|a0| and 9 |a0| / T conservatively)."""
    v0, a0 = np.abs(np.asarray(v0, float)), np.abs(np.asarray(a0, float))
    A, J = budget * np.asarray(acc, float), budget * np.asarray(jerk, float)
    T = max(minimum, float(np.max((1.5 * v0 + 2.0 * a0 * minimum) / A)))
    T = max(T, float(np.max(np.sqrt((6.0 * v0 + 9.0 * a0 * T) / J))))
    return T


__all__ = ["Hold", "Spline", "Blend", "StopCurve", "smoothstep", "stop_duration", "W1_MAX", "W2_MAX", "W3_MAX"]
