"""Forward kinematics of the UR arms in plain Python floats, for the per-cycle safety checks.

`sim.kinematics.Kinematics.fk` builds batched 4x4 arrays (~90 us a call); the filter needs the TCP pose and a
few gripper points every 2 ms, so this writes the standard-DH chain out in closed form (~4 us). Joints 2-4
are parallel, so the chain is a planar arm in the frame of joint 1. `frames` also returns every joint's axis
and a point on it, from which the Jacobian column of any point P is axis_i x (P - origin_i).
Agreement with `sim.kinematics` is tested to 1e-12.
"""

from __future__ import annotations

from math import acos, cos, sin


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

    def pose(self, q):
        """(px, py, pz, R) with R the rotation as a row-major 9-tuple."""
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
        return c1 * px1 + s1 * pz1, s1 * px1 - c1 * pz1, self.d1 + py1, R

    def frames(self, q):
        """(P, R, axes, origins): TCP position and rotation, and each joint's unit axis and a point on it."""
        q1, q2, q3, q4, q5, q6 = q
        s1, c1 = sin(q1), cos(q1)
        q23 = q2 + q3
        q234 = q23 + q4
        s2, c2, s23, c23 = sin(q2), cos(q2), sin(q23), cos(q23)
        s234, c234, s5, c5 = sin(q234), cos(q234), sin(q5), cos(q5)
        X = self.a2 * c2 + self.a3 * c23
        Y = self.a2 * s2 + self.a3 * s23
        d1, d4, d5 = self.d1, self.d4, self.d5
        px, py, pz, R = self.pose(q)
        a_par = (s1, -c1, 0.0)
        a5 = (c1 * s234, s1 * s234, -c234)
        a6 = (R[2], R[5], R[8])
        o4 = (c1 * X + s1 * d4, s1 * X - c1 * d4, d1 + Y)
        axes = ((0.0, 0.0, 1.0), a_par, a_par, a_par, a5, a6)
        origins = ((0.0, 0.0, 0.0), (0.0, 0.0, d1), (c1 * self.a2 * c2, s1 * self.a2 * c2, d1 + self.a2 * s2),
                   (c1 * X, s1 * X, d1 + Y), o4,
                   (o4[0] + d5 * a5[0], o4[1] + d5 * a5[1], o4[2] + d5 * a5[2]))
        return (px, py, pz), R, axes, origins


    def solve(self, p, R, seed, iters: int = 8, tol: float = 1e-11, max_step: float = 0.5,
              max_dev: float = 0.3):
        """Joint angles reaching TCP pose (p, R) by Newton steps from `seed` (stays on the seed's branch).

        Returns a list, or None when it does not converge or lands more than `max_dev` rad from the seed
        (far target, near a singularity): the caller then uses the analytic IK nearest the seed.
        """
        import numpy as np

        q = [float(x) for x in seed]
        J = np.empty((6, 6))
        err = np.empty(6)
        for _ in range(iters):
            P, Rq, axes, origins = self.frames(q)
            err[0], err[1], err[2] = p[0] - P[0], p[1] - P[1], p[2] - P[2]
            # orientation error: vee of (R Rq^T - Rq R^T) / 2 ~ rotation vector for small errors
            E = _mul_t(R, Rq)
            err[3], err[4], err[5] = 0.5 * (E[7] - E[5]), 0.5 * (E[2] - E[6]), 0.5 * (E[3] - E[1])
            if E[0] + E[4] + E[8] < 1.0:  # more than 90 degrees off: not Newton's job
                return None
            if float(np.abs(err).max()) < tol:
                return q if max(abs(q[i] - seed[i]) for i in range(6)) <= max_dev else None
            for i in range(6):
                ax, o = axes[i], origins[i]
                rx, ry, rz = P[0] - o[0], P[1] - o[1], P[2] - o[2]
                J[0, i] = ax[1] * rz - ax[2] * ry
                J[1, i] = ax[2] * rx - ax[0] * rz
                J[2, i] = ax[0] * ry - ax[1] * rx
                J[3, i], J[4, i], J[5, i] = ax
            try:
                dq = np.linalg.solve(J, err)
            except np.linalg.LinAlgError:
                return None
            big = float(np.abs(dq).max())
            if not big < max_step:  # also catches NaN
                return None
            q = [q[i] + float(dq[i]) for i in range(6)]
        return None


def _mul_t(A, B):
    """A @ B^T for row-major 9-tuples."""
    return tuple(A[3 * r] * B[3 * c] + A[3 * r + 1] * B[3 * c + 1] + A[3 * r + 2] * B[3 * c + 2]
                 for r in range(3) for c in range(3))


def transform_point(p, R, offset):
    """World position of a point given in the TCP frame."""
    x, y, z = offset
    return (p[0] + R[0] * x + R[1] * y + R[2] * z,
            p[1] + R[3] * x + R[4] * y + R[5] * z,
            p[2] + R[6] * x + R[7] * y + R[8] * z)


def rotation_angle(Ra, Rb) -> float:
    """Angle (rad) of Ra^T Rb, for row-major 9-tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = Ra
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = Rb
    c = 0.5 * (a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3 + a4 * b4 + a5 * b5 + a6 * b6 + a7 * b7 + a8 * b8 - 1.0)
    return acos(1.0 if c > 1.0 else (-1.0 if c < -1.0 else c))


__all__ = ["FastKinematics", "transform_point", "rotation_angle"]
