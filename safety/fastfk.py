"""Forward kinematics of the UR arms in plain Python floats, for the per-cycle safety checks.

The filter needs the TCP pose and a few gripper points every 2 ms, so this writes the standard-DH chain out in
closed form (~4 us). It predates the scalar path of `sim.kinematics.Kinematics.fk` (now ~6 us; it was ~90 us
through batched arrays) and still adds what the filter uses beyond a pose: joint axes and points. Joints 2-4
are parallel, so the chain is a planar arm in the frame of joint 1. `frames` also returns every joint's axis
and a point on it, from which the Jacobian column of any point P is axis_i x (P - origin_i).
Agreement with `sim.kinematics` is tested to 1e-12.
"""

from __future__ import annotations

from math import acos, cos, sin, sqrt

from numpy import array as _array
from numpy import errstate as _errstate
from numpy.linalg import LinAlgError
from numpy.linalg import solve as _solve

try:  # the LAPACK gesv gufunc behind numpy.linalg.solve, without its ~4 us of Python wrapping (same result)
    from numpy.linalg._umath_linalg import solve1 as _gesv
except ImportError:  # pragma: no cover - a numpy without it: the public function
    _gesv = None


class FastKinematics:
    """TCP pose of one UR variant with the TCP `tcp_z` metres out along the flange z axis."""

    def __init__(self, variant, tcp_z: float):
        self.d1, self.a2, self.a3 = float(variant.d1), float(variant.a2), float(variant.a3)
        self.d4, self.d5, self.d6 = float(variant.d4), float(variant.d5), float(variant.d6)
        self.L = self.d6 + float(tcp_z)
        # Upper bounds of the distance from joint axis i to the TCP or a point within `reach_pad` of it
        # (triangle inequality along the chain from a point on that axis): the Lipschitz constants of the
        # point's position in each joint angle.
        tail = [self.d1 + abs(self.a2) + abs(self.a3) + self.d4 + self.d5, abs(self.a2) + abs(self.a3) + self.d4 + self.d5,
                abs(self.a3) + self.d4 + self.d5, self.d4 + self.d5, self.d5, 0.0]
        self.axis_reach = tuple(t + self.L for t in tail[:5]) + (0.0,)  # the TCP lies on the wrist 3 axis
        self.iterations = 0  # Newton iterations of the last solve

    def pose(self, q):
        """(px, py, pz, R) with R the rotation as a row-major 9-tuple."""
        px, py, pz, R, _ = self._chain(q)
        return px, py, pz, R

    def frames(self, q):
        """(P, R, axes, origins): TCP position and rotation, and each joint's unit axis and a point on it."""
        px, py, pz, R, (s1, c1, s2, c2, X, Y, s234, c234) = self._chain(q)
        d1, d4, d5 = self.d1, self.d4, self.d5
        a_par = (s1, -c1, 0.0)
        a5 = (c1 * s234, s1 * s234, -c234)
        a6 = (R[2], R[5], R[8])
        o4 = (c1 * X + s1 * d4, s1 * X - c1 * d4, d1 + Y)
        axes = ((0.0, 0.0, 1.0), a_par, a_par, a_par, a5, a6)
        origins = ((0.0, 0.0, 0.0), (0.0, 0.0, d1), (c1 * self.a2 * c2, s1 * self.a2 * c2, d1 + self.a2 * s2),
                   (c1 * X, s1 * X, d1 + Y), o4,
                   (o4[0] + d5 * a5[0], o4[1] + d5 * a5[1], o4[2] + d5 * a5[2]))
        return (px, py, pz), R, axes, origins

    def _chain(self, q):
        """The chain in closed form: px, py, pz, R and the terms frames() reuses (each trig function once)."""
        q1, q2, q3, q4, q5, q6 = q
        s1, c1 = sin(q1), cos(q1)
        q23 = q2 + q3
        q234 = q23 + q4
        s2, c2, s23, c23 = sin(q2), cos(q2), sin(q23), cos(q23)
        s234, c234, s5, c5, s6, c6 = sin(q234), cos(q234), sin(q5), cos(q5), sin(q6), cos(q6)
        L, d5 = self.L, self.d5
        X = self.a2 * c2 + self.a3 * c23
        Y = self.a2 * s2 + self.a3 * s23
        px1 = X - L * s5 * c234 + d5 * s234
        py1 = Y - L * s5 * s234 - d5 * c234
        pz1 = self.d4 + L * c5
        c5c6, c5s6 = c5 * c6, c5 * s6
        xx, xy, xz = c5c6 * c234 - s6 * s234, c5c6 * s234 + s6 * c234, s5 * c6
        yx, yy, yz = -c5s6 * c234 - c6 * s234, -c5s6 * s234 + c6 * c234, -s5 * s6
        zx, zy, zz = -s5 * c234, -s5 * s234, c5
        R = (c1 * xx + s1 * xz, c1 * yx + s1 * yz, c1 * zx + s1 * zz,
             s1 * xx - c1 * xz, s1 * yx - c1 * yz, s1 * zx - c1 * zz,
             xy, yy, zy)
        return (c1 * px1 + s1 * pz1, s1 * px1 - c1 * pz1, self.d1 + py1, R,
                (s1, c1, s2, c2, X, Y, s234, c234))

    def solve(self, p, R, seed, iters: int = 8, tol: float = 1e-11, max_step: float = 0.5,
              max_dev: float = 0.3):
        """Joint angles reaching TCP pose (p, R) by Newton steps from `seed` (stays on the seed's branch).

        At most `iters` iterations (~15 us each; `self.iterations` says how many ran). Returns a list, or None
        when it does not converge within them, a step exceeds `max_step` (far target, near a singularity) or
        it lands more than `max_dev` rad from the seed (another branch).
        """
        q = [float(x) for x in seed]
        self.iterations = 0
        with _errstate(all="ignore"):  # a singular Jacobian gives NaN steps, rejected below
            return self._newton(q, p, R, seed, iters, tol, max_step, max_dev)

    def _newton(self, q, p, R, seed, iters, tol, max_step, max_dev):
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = R
        for _ in range(iters):
            self.iterations += 1
            P, Rq, axes, origins = self.frames(q)
            b0, b1, b2, b3, b4, b5, b6, b7, b8 = Rq
            # orientation error: vee of (R Rq^T - Rq R^T) / 2 ~ rotation vector for small errors
            if (r0 * b0 + r1 * b1 + r2 * b2) + (r3 * b3 + r4 * b4 + r5 * b5) + (r6 * b6 + r7 * b7 + r8 * b8) < 1.0:
                return None  # more than 90 degrees off: not Newton's job
            err = [p[0] - P[0], p[1] - P[1], p[2] - P[2],
                   0.5 * ((r6 * b3 + r7 * b4 + r8 * b5) - (r3 * b6 + r4 * b7 + r5 * b8)),
                   0.5 * ((r0 * b6 + r1 * b7 + r2 * b8) - (r6 * b0 + r7 * b1 + r8 * b2)),
                   0.5 * ((r3 * b0 + r4 * b1 + r5 * b2) - (r0 * b3 + r1 * b4 + r2 * b5))]
            for e in err:
                if not (e < tol and -e < tol):  # also catches NaN
                    break
            else:
                for i in range(6):
                    d = q[i] - seed[i]
                    if d > max_dev or d < -max_dev:
                        return None
                return q
            Px, Py, Pz = P
            cols = []
            for i in range(6):
                ax, o = axes[i], origins[i]
                rx, ry, rz = Px - o[0], Py - o[1], Pz - o[2]
                cols.append((ax[1] * rz - ax[2] * ry, ax[2] * rx - ax[0] * rz, ax[0] * ry - ax[1] * rx,
                             ax[0], ax[1], ax[2]))
            J = _array(cols).T
            try:
                dq = (_gesv(J, _array(err)) if _gesv is not None else _solve(J, err)).tolist()
            except LinAlgError:
                return None
            for d in dq:
                if not (d < max_step and -d < max_step):  # also catches NaN
                    return None
            q = [q[i] + dq[i] for i in range(6)]
        return None


def transform_point(p, R, offset):
    """World position of a point given in the TCP frame."""
    x, y, z = offset
    return (p[0] + R[0] * x + R[1] * y + R[2] * z,
            p[1] + R[3] * x + R[4] * y + R[5] * z,
            p[2] + R[6] * x + R[7] * y + R[8] * z)


def tcp_speeds(cur, nxt, dt: float) -> tuple[float, float]:
    """(linear m/s, angular rad/s) of the TCP moving from pose `cur` to pose `nxt` (fk.pose tuples) in dt."""
    lin = sqrt((nxt[0] - cur[0]) ** 2 + (nxt[1] - cur[1]) ** 2 + (nxt[2] - cur[2]) ** 2) / dt
    return lin, rotation_angle(cur[3], nxt[3]) / dt


def rotation_angle(Ra, Rb) -> float:
    """Angle (rad) of Ra^T Rb, for row-major 9-tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = Ra
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = Rb
    c = 0.5 * (a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3 + a4 * b4 + a5 * b5 + a6 * b6 + a7 * b7 + a8 * b8 - 1.0)
    return acos(1.0 if c > 1.0 else (-1.0 if c < -1.0 else c))


__all__ = ["FastKinematics", "transform_point", "rotation_angle", "tcp_speeds"]
