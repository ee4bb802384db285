"""Closed-form kinematics of the UR arms (standard DH), in the UR controller's base frame.

Why analytic: the runtime must map a TCP pose to joint angles every control cycle, deterministically and
with all eight branches visible, so that it can stay on the branch the robot is already on (a numeric
solver may silently jump to another elbow/wrist configuration). The chain is
T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i); `fk_flange` ends at the tool flange, `fk` at the TCP.
Poses use UR's axis-angle (rotation vector) convention, as in `getActualTCPPose`.

The single-configuration calls (`fk`, `fk_flange`, `jacobian`, `ik_all`, `ik`) run in plain Python floats
with `math` (~6 us for fk, ~50 us for ik, against ~100 / ~600 us through numpy's per-call overhead on 4x4
arrays); `fk_batch` / `frames_batch` and `_solve_numpy` are the batched numpy forms they are tested against,
inherited from `sim.kinematics_numpy.NumpyKinematics`. The rotation-vector and pose helpers live in
`sim.rotations` and are re-exported here.
"""

from __future__ import annotations

from math import acos, atan2, cos, hypot, isfinite, pi, sin, sqrt

import numpy as np

from sim.kinematics_numpy import SINGULAR, TOL, NumpyKinematics
from sim.robot import RobotVariant
from sim.rotations import (  # noqa: F401 - re-exported: `from sim.kinematics import rotvec_to_matrix` etc.
    matrix_to_pose,
    matrix_to_rotvec,
    pose_to_matrix,
    rotvec_to_matrix,
    wrap_angle,
)

_TWO_PI = 2 * pi
_HALF_PI = pi / 2
_NAN_ROW = [float("nan")] * 6


class UnreachableError(ValueError):
    """The target pose has no inverse-kinematics solution for this arm; the message says why and what to do."""


def _finite(x: np.ndarray) -> bool:
    """All entries finite (the scalar paths use `math`, which raises on inf where numpy gives NaN)."""
    s = float(x.sum())
    return s - s == 0.0  # NaN for any NaN or inf entry (a finite sum overflowing only sends us the slow way)


def _wrap(a: float) -> float:
    """wrap_angle for one float, bit-identical (Python's float % is numpy's np.mod)."""
    return pi - (pi - a) % _TWO_PI


def _to_matrix(F: tuple) -> np.ndarray:
    """(x, y, z axes, origin) as 12 floats -> 4x4 homogeneous transform."""
    xx, xy, xz, yx, yy, yz, zx, zy, zz, px, py, pz = F
    return np.array([xx, yx, zx, px, xy, yy, zy, py, xz, yz, zz, pz, 0.0, 0.0, 0.0, 1.0]).reshape(4, 4)


class Kinematics(NumpyKinematics):
    """FK, all-branch analytic IK and the Jacobian of one UR variant with a fixed flange->TCP transform."""

    def __init__(self, variant: RobotVariant | str = "ur5e", tcp_offset=None):
        super().__init__(variant, tcp_offset)
        # Plain-float copies for the single-configuration paths (fk, fk_flange, jacobian, ik_all, ik), which
        # write the chain out in scalar `math`: numpy's per-call overhead on 4x4 arrays dominates otherwise.
        # They rely on the UR structure (alpha = [pi/2, 0, 0, pi/2, -pi/2, 0], a1 = a4 = a5 = a6 = 0, as the
        # IK does anyway); for any other chain fk/fk_flange/jacobian use the batched path.
        self._d1, self._d4, self._d5, self._d6 = (float(self.d[i]) for i in (0, 3, 4, 5))
        self._a2, self._a3 = float(self.a[1]), float(self.a[2])
        self._scalar_ok = bool(
            np.array_equal(self.alpha, [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
            and not self.a[[0, 3, 4, 5]].any() and not self.d[[1, 2]].any())
        self._tcp = [float(x) for x in self.tcp_offset[:3].ravel()]  # row-major 3x4
        self._tcp_inv_l = [float(x) for x in self._tcp_inv[:3].ravel()]
        self._tcp_rot_eye = bool((self.tcp_offset[:3, :3] == np.eye(3)).all())
        self._lo = [float(x) - TOL for x in self.lower]
        self._hi = [float(x) + TOL for x in self.upper]
        self._lower_l, self._upper_l = self.lower.tolist(), self.upper.tolist()

    @classmethod
    def with_tcp_z(cls, variant: RobotVariant | str, z: float) -> Kinematics:
        """A TCP `z` metres out along the flange z axis, same orientation (e.g. a gripper's pinch point)."""
        T = np.eye(4)
        T[2, 3] = z
        return cls(variant, T)

    # ---- forward kinematics (batched forms: NumpyKinematics) --------------------------------------
    def fk_flange(self, q) -> np.ndarray:
        """Base->flange 4x4 transform at joint angles q."""
        q = np.asarray(q, dtype=float).reshape(6)
        if not self._scalar_ok or not _finite(q):
            return self.fk_flange_batch(q[None])[0]
        return _to_matrix(self._chain(q.tolist()))

    def fk(self, q) -> np.ndarray:
        """Base->TCP 4x4 transform at joint angles q."""
        q = np.asarray(q, dtype=float).reshape(6)
        if not self._scalar_ok or not _finite(q):
            return self.fk_batch(q[None])[0]
        return _to_matrix(self._to_tcp(self._chain(q.tolist())))

    def jacobian(self, q) -> np.ndarray:
        """6x6 geometric Jacobian at the TCP, base frame: rows 0-2 linear velocity, rows 3-5 angular."""
        q = np.asarray(q, dtype=float).reshape(6)
        if not self._scalar_ok or not _finite(q):
            F = self.frames_batch(q[None])[0]
            p = (F[6] @ self.tcp_offset)[:3, 3]
            z, o = F[:6, :3, 2], F[:6, :3, 3]
            return np.vstack([np.cross(z, p - o).T, z.T])
        axes = []
        flange = self._chain(q.tolist(), axes)
        px, py, pz = self._to_tcp(flange)[9:]
        vx, vy, vz, wx, wy, wz = [], [], [], [], [], []
        for zx, zy, zz, ox, oy, oz in axes:  # column i: z_i x (p - o_i), z_i
            rx, ry, rz = px - ox, py - oy, pz - oz
            vx.append(zy * rz - zz * ry)
            vy.append(zz * rx - zx * rz)
            vz.append(zx * ry - zy * rx)
            wx.append(zx)
            wy.append(zy)
            wz.append(zz)
        return np.array([vx, vy, vz, wx, wy, wz])

    def _chain(self, q, axes=None) -> tuple:
        """The flange frame at q (a list of 6 floats) in scalar math, as (x, y, z axes, origin): 12 floats.

        Structured DH product: joints 2-4 are parallel, so frames 1-3 live in the arm plane spanned by
        e = (c1, s1, 0) and the base z axis, with normal n = (s1, -c1, 0); the +-pi/2 twists only permute
        axes. If `axes` is a list, (axis z_i, origin o_i) of frames 0..5 are appended to it (Jacobian).
        """
        q1, q2, q3, q4, q5, q6 = q
        d1, d4, d5, d6, a2, a3 = self._d1, self._d4, self._d5, self._d6, self._a2, self._a3
        c1, s1 = cos(q1), sin(q1)
        c2, s2 = cos(q2), sin(q2)
        c3, s3 = cos(q3), sin(q3)
        c4, s4 = cos(q4), sin(q4)
        # in-plane (radial, vertical) components of the x axes of frames 2, 3, 4 and the origins of 2, 3
        C3, S3 = c3 * c2 - s3 * s2, c3 * s2 + s3 * c2
        C4, S4 = c4 * C3 - s4 * S3, c4 * S3 + s4 * C3
        X2, Y2 = a2 * c2, d1 + a2 * s2
        X3, Y3 = X2 + a3 * C3, Y2 + a3 * S3
        # frame 4: x4 = C4 e + S4 k, y4 = n, z4 = S4 e - C4 k, o4 = X3 e + Y3 k + d4 n
        x4x, x4y, x4z = C4 * c1, C4 * s1, S4
        z4x, z4y, z4z = S4 * c1, S4 * s1, -C4
        o4x, o4y, o4z = X3 * c1 + d4 * s1, X3 * s1 - d4 * c1, Y3
        # frame 5: Rz(q5) Tz(d5) Rx(-pi/2)
        c5, s5 = cos(q5), sin(q5)
        o5x, o5y, o5z = o4x + d5 * z4x, o4y + d5 * z4y, o4z + d5 * z4z
        x5x, x5y, x5z = c5 * x4x + s5 * s1, c5 * x4y - s5 * c1, c5 * x4z
        z5x, z5y, z5z = c5 * s1 - s5 * x4x, -c5 * c1 - s5 * x4y, -s5 * x4z  # y5 = -z4
        # frame 6: Rz(q6) Tz(d6)
        c6, s6 = cos(q6), sin(q6)
        if axes is not None:
            axes += [(0.0, 0.0, 1.0, 0.0, 0.0, 0.0), (s1, -c1, 0.0, 0.0, 0.0, d1),
                     (s1, -c1, 0.0, X2 * c1, X2 * s1, Y2), (s1, -c1, 0.0, X3 * c1, X3 * s1, Y3),
                     (z4x, z4y, z4z, o4x, o4y, o4z), (z5x, z5y, z5z, o5x, o5y, o5z)]
        return (c6 * x5x - s6 * z4x, c6 * x5y - s6 * z4y, c6 * x5z - s6 * z4z,
                -c6 * z4x - s6 * x5x, -c6 * z4y - s6 * x5y, -c6 * z4z - s6 * x5z,
                z5x, z5y, z5z,
                o5x + d6 * z5x, o5y + d6 * z5y, o5z + d6 * z5z)

    def _to_tcp(self, F: tuple) -> tuple:
        """Flange frame (x, y, z axes, origin: 12 floats) -> TCP frame, i.e. F @ tcp_offset."""
        xx, xy, xz, yx, yy, yz, zx, zy, zz, px, py, pz = F
        r00, r01, r02, tx, r10, r11, r12, ty, r20, r21, r22, tz = self._tcp
        px, py, pz = (xx * tx + yx * ty + zx * tz + px, xy * tx + yy * ty + zy * tz + py,
                      xz * tx + yz * ty + zz * tz + pz)
        if self._tcp_rot_eye:
            return xx, xy, xz, yx, yy, yz, zx, zy, zz, px, py, pz
        return (xx * r00 + yx * r10 + zx * r20, xy * r00 + yy * r10 + zy * r20, xz * r00 + yz * r10 + zz * r20,
                xx * r01 + yx * r11 + zx * r21, xy * r01 + yy * r11 + zy * r21, xz * r01 + yz * r11 + zz * r21,
                xx * r02 + yx * r12 + zx * r22, xy * r02 + yy * r12 + zy * r22, xz * r02 + yz * r12 + zz * r22,
                px, py, pz)

    # ---- inverse kinematics -------------------------------------------------------------------------
    def _solve(self, T, q6_hint: float) -> tuple[list, str]:
        """All 8 branches for TCP pose T in scalar math: ([8 rows of 6 floats, or None], why).

        Row index = 4*shoulder + 2*wrist + elbow. The same steps as `_solve_numpy`, with the products
        T14 = T01^-1 T06 T46^-1 and T34 = T13^-1 T14 reduced to the entries the solution reads.
        """
        T = np.asarray(T, dtype=float)
        if not self._scalar_ok or not _finite(T[:3]) or q6_hint - q6_hint != 0.0:
            Q, valid, why = self._solve_numpy(T, q6_hint)
            return [row if ok else None for row, ok in zip(Q.tolist(), valid.tolist())], why
        (t00, t01, t02, t03), (t10, t11, t12, t13), (t20, t21, t22, t23) = T[:3].tolist()
        # T06 = T @ tcp_offset^-1
        r00, r01, r02, ux, r10, r11, r12, uy, r20, r21, r22, uz = self._tcp_inv_l
        px = t00 * ux + t01 * uy + t02 * uz + t03
        py = t10 * ux + t11 * uy + t12 * uz + t13
        pz = t20 * ux + t21 * uy + t22 * uz + t23
        if self._tcp_rot_eye:
            R00, R01, R02, R10, R11, R12, R20, R21, R22 = t00, t01, t02, t10, t11, t12, t20, t21, t22
        else:
            R00, R01, R02 = (t00 * r00 + t01 * r10 + t02 * r20, t00 * r01 + t01 * r11 + t02 * r21,
                             t00 * r02 + t01 * r12 + t02 * r22)
            R10, R11, R12 = (t10 * r00 + t11 * r10 + t12 * r20, t10 * r01 + t11 * r11 + t12 * r21,
                             t10 * r02 + t11 * r12 + t12 * r22)
            R20, R21, R22 = (t20 * r00 + t21 * r10 + t22 * r20, t20 * r01 + t21 * r11 + t22 * r21,
                             t20 * r02 + t21 * r12 + t22 * r22)
        d1, d4, d5, d6, a2, a3 = self._d1, self._d4, self._d5, self._d6, self._a2, self._a3
        rows: list = [None] * 8
        p05x, p05y = px - d6 * R02, py - d6 * R12  # wrist centre: the axis-5 point
        r = hypot(p05x, p05y)
        if r < d4 - TOL:
            return rows, (
                f"the wrist centre would be {r:.3f} m from the base z axis, closer than the {self.variant.name}'s "
                f"shoulder offset d4 = {d4:.4f} m allows; move the target away from the base axis")
        psi = acos(min(d4 / r, 1.0))
        phi = atan2(p05y, p05x)
        a2sq_a3sq, two_a2a3 = a2 * a2 + a3 * a3, 2 * a2 * a3
        L_bad = None
        for s_i, sgn1 in ((0, 1.0), (4, -1.0)):
            q1 = phi + sgn1 * psi + _HALF_PI
            s1, c1 = sin(q1), cos(q1)
            c5 = R02 * s1 - R12 * c1  # R[:, 2] . n, n = (s1, -c1, 0): normal of the arm plane
            x, y = R00 * s1 - R10 * c1, R11 * c1 - R01 * s1
            s5abs = hypot(x, y)  # == sqrt(1 - c5^2), but accurate near the singularity
            # rows 0 and 1 of R01^T R06 and of R01^T (p06 - p01)
            A00, A01, A02 = c1 * R00 + s1 * R10, c1 * R01 + s1 * R11, c1 * R02 + s1 * R12
            pA0, pA1 = c1 * px + s1 * py, pz - d1
            q1w = _wrap(q1)
            for w_i, sgn5 in ((0, 1.0), (2, -1.0)):
                q5 = atan2(sgn5 * s5abs, c5)
                q6 = q6_hint if s5abs < SINGULAR else atan2(sgn5 * y, sgn5 * x)
                cq5, sq5, cq6, sq6 = cos(q5), sin(q5), cos(q6), sin(q6)
                # T14 = T01^-1 T06 T46^-1: with u = R46^T p46 = (-s6 d5, -c6 d5, d6), p14 = pA - R_A u, and
                # R14[:, 0] = R_A R46[0, :]^T, R46[0, :] = (c5 c6, -c5 s6, -s5)
                u0, u1 = -sq6 * d5, -cq6 * d5
                e0, e1 = cq5 * cq6, -cq5 * sq6
                px14 = pA0 - (A00 * u0 + A01 * u1 + A02 * d6)  # frame 1's x-y plane is the arm plane
                py14 = pA1 - (R20 * u0 + R21 * u1 + R22 * d6)
                R14_00 = A00 * e0 + A01 * e1 - A02 * sq5
                R14_10 = R20 * e0 + R21 * e1 - R22 * sq5
                L = hypot(px14, py14)  # shoulder joint to wrist-1 axis, in the arm plane
                c3 = (L * L - a2sq_a3sq) / two_a2a3
                if abs(c3) > 1 + TOL:
                    L_bad = L
                    continue
                ang = atan2(py14, px14)
                tail = [_wrap(q5), _wrap(q6)]
                for e_i, sgn3 in ((0, 1.0), (1, -1.0)):
                    q3 = sgn3 * acos(1.0 if c3 > 1.0 else -1.0 if c3 < -1.0 else c3)
                    cq3, sq3 = cos(q3), sin(q3)
                    q2 = ang - atan2(a3 * sq3, a2 + a3 * cq3)
                    cq2, sq2 = cos(q2), sin(q2)
                    C, S = cq2 * cq3 - sq2 * sq3, sq2 * cq3 + cq2 * sq3  # R13 = Rz(q2 + q3)
                    q4 = atan2(C * R14_10 - S * R14_00, C * R14_00 + S * R14_10)  # T34 = T13^-1 T14
                    rows[s_i + w_i + e_i] = [q1w, _wrap(q2), _wrap(q3), _wrap(q4)] + tail
        why = ""
        if L_bad is not None and rows.count(None) == 8:
            reach, inner = abs(a2) + abs(a3), abs(abs(a2) - abs(a3))
            dist = sqrt(t03 * t03 + t13 * t13 + t23 * t23)
            side = "at most" if L_bad > reach else "at least"
            why = (f"target {dist:.3f} m from the base origin puts the wrist {L_bad:.3f} m from the shoulder "
                   f"joint; the {self.variant.name}'s upper arm + forearm reach {side} "
                   f"{reach if L_bad > reach else inner:.3f} m there; "
                   + ("bring the target closer to the base" if L_bad > reach else "move the target farther out"))
        return rows, why

    def ik_all(self, T, q6_hint: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """All 8 analytic IK branches of TCP pose T as ((8, 6) angles in (-pi, pi], (8,) valid mask).

        Row index = 4*shoulder + 2*wrist + elbow (0/1 each); rows for branches that do not exist are NaN.
        At a wrist singularity (sin q5 ~ 0) only q4 + q6 is defined; q6 is then set to `q6_hint`.
        """
        rows, _ = self._solve(T, float(q6_hint))
        return (np.array([_NAN_ROW if row is None else row for row in rows]),
                np.array([row is not None for row in rows]))

    def ik(self, T, q_current) -> np.ndarray:
        """The valid IK solution nearest q_current (Euclidean in joint space), unwrapped within limits.

        Each joint takes the 2*pi-equivalent angle, within the variant's joint limits, nearest its current
        value, so a continuous path of poses gives a continuous joint path. Raises UnreachableError.
        """
        qc = np.asarray(q_current, dtype=float).reshape(6).tolist()
        rows, why = self._solve(T, qc[5])
        sols = [row for row in rows if row is not None]
        if not sols:
            raise UnreachableError(f"no IK solution: {why}")
        lo, hi = self._lo, self._hi
        best, best_cost = None, None
        q_finite = all(map(isfinite, qc))  # a NaN or inf current angle leaves no candidate within limits
        for row in sols if q_finite else ():
            sol, cost = [], 0.0
            for j in range(6):
                qj, cj = row[j], qc[j]
                k0 = round((cj - qj) / _TWO_PI)
                pick, err = None, None
                for k in (k0 - 1, k0, k0 + 1):  # the nearest in-limit 2*pi-equivalent; first of equals wins
                    cand = qj + _TWO_PI * k
                    if lo[j] <= cand <= hi[j]:
                        e = abs(cand - cj)
                        if err is None or e < err:
                            pick, err = cand, e
                if pick is None:
                    break
                sol.append(pick)
                cost += err * err
            else:
                if best_cost is None or cost < best_cost:
                    best, best_cost = sol, cost
        if best is None:
            raise UnreachableError(
                f"the {self.variant.name} reaches this pose in {len(sols)} configuration(s), but none within its "
                f"joint limits; choose another TCP orientation or unwind the wrist first")
        lower, upper = self._lower_l, self._upper_l
        return np.array([lower[j] if v < lower[j] else upper[j] if v > upper[j] else v
                         for j, v in enumerate(best)])  # np.clip
