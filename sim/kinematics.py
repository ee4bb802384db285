"""Closed-form kinematics of the UR arms (standard DH), in the UR controller's base frame.

Why analytic: the runtime must map a TCP pose to joint angles every control cycle, deterministically and
with all eight branches visible, so that it can stay on the branch the robot is already on (a numeric
solver may silently jump to another elbow/wrist configuration). The chain is
T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i); `fk_flange` ends at the tool flange, `fk` at the TCP.
Poses use UR's axis-angle (rotation vector) convention, as in `getActualTCPPose`.
"""

from __future__ import annotations

import numpy as np

from sim.robot import RobotVariant, get_variant

_SINGULAR = 1e-10  # |sin q5| below this: wrist axes 4 and 6 align, q4 + q6 is all that is defined
_TOL = 1e-9  # slack on acos arguments and joint limits for targets exactly on a boundary


class UnreachableError(ValueError):
    """The target pose has no inverse-kinematics solution for this arm; the message says why and what to do."""


def wrap_angle(a):
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2 * np.pi)


def rotvec_to_matrix(rotvec) -> np.ndarray:
    """Rodrigues' formula, with a Taylor expansion near 0 so tiny rotations stay exact."""
    r = np.asarray(rotvec, dtype=float)
    th = np.linalg.norm(r)
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if th < 1e-6:
        a, b = 1.0 - th**2 / 6.0, 0.5 - th**2 / 24.0
    else:
        a, b = np.sin(th) / th, (1.0 - np.cos(th)) / th**2
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R) -> np.ndarray:
    """Rotation vector (angle in [0, pi]) of a rotation matrix, via a Shepperd quaternion.

    Going through the quaternion keeps the result accurate near pi, where the usual
    acos((trace - 1) / 2) / skew-part formula loses the axis.
    """
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    i = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        w = 0.5 * np.sqrt(max(1.0 + tr, 0.0))
        v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (4 * w)
    else:
        j, k = i % 3, (i + 1) % 3  # i-1 is the dominant axis; (i-1, j, k) cyclic
        m = i - 1
        vm = 0.5 * np.sqrt(max(1.0 + 2 * R[m, m] - tr, 0.0))
        v = np.empty(3)
        v[m] = vm
        v[j] = (R[j, m] + R[m, j]) / (4 * vm)
        v[k] = (R[k, m] + R[m, k]) / (4 * vm)
        w = (R[k, j] - R[j, k]) / (4 * vm)
    if w < 0:
        w, v = -w, -v  # the short way round: angle in [0, pi]
    s = np.linalg.norm(v)
    if s < 1e-12:
        return 2.0 * v / max(w, 1e-300)  # theta ~ 2 s / w for tiny rotations
    return 2.0 * np.arctan2(s, w) * v / s


def pose_to_matrix(pos, rotvec=None) -> np.ndarray:
    """4x4 transform from a position and rotation vector, or from one UR pose [x, y, z, rx, ry, rz]."""
    pos = np.asarray(pos, dtype=float)
    if rotvec is None:
        pos, rotvec = pos[:3], pos[3:6]
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(rotvec)
    T[:3, 3] = pos
    return T


def matrix_to_pose(T) -> tuple[np.ndarray, np.ndarray]:
    """(position, rotation vector) of a 4x4 transform; np.concatenate them for a UR pose."""
    T = np.asarray(T, dtype=float)
    return T[:3, 3].copy(), matrix_to_rotvec(T[:3, :3])


def _dh(theta, d, a, alpha) -> np.ndarray:
    """Standard DH transforms Rz(theta) Tz(d) Tx(a) Rx(alpha), batched over theta's shape."""
    theta = np.asarray(theta, dtype=float)
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    T = np.zeros(theta.shape + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 0, 2], T[..., 0, 3] = ct, -st * ca, st * sa, a * ct
    T[..., 1, 0], T[..., 1, 1], T[..., 1, 2], T[..., 1, 3] = st, ct * ca, -ct * sa, a * st
    T[..., 2, 1], T[..., 2, 2], T[..., 2, 3] = sa, ca, d
    T[..., 3, 3] = 1.0
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


class Kinematics:
    """FK, all-branch analytic IK and the Jacobian of one UR variant with a fixed flange->TCP transform."""

    def __init__(self, variant: RobotVariant | str = "ur5e", tcp_offset=None):
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        v = self.variant
        self.d, self.a, self.alpha = v.dh_d, v.dh_a, v.dh_alpha
        self.tcp_offset = np.eye(4) if tcp_offset is None else np.asarray(tcp_offset, dtype=float).copy()
        self._tcp_inv = _inv(self.tcp_offset)
        self.lower, self.upper = np.array(v.joint_lower), np.array(v.joint_upper)

    @classmethod
    def with_tcp_z(cls, variant: RobotVariant | str, z: float) -> Kinematics:
        """A TCP `z` metres out along the flange z axis, same orientation (e.g. a gripper's pinch point)."""
        T = np.eye(4)
        T[2, 3] = z
        return cls(variant, T)

    # ---- forward kinematics -------------------------------------------------------------------------
    def frames_batch(self, Q) -> np.ndarray:
        """(N, 7, 4, 4): base->frame_i for i = 0..6 (frame 6 is the flange)."""
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        out = np.empty((Q.shape[0], 7, 4, 4))
        out[:, 0] = np.eye(4)
        for i in range(6):
            out[:, i + 1] = out[:, i] @ _dh(Q[:, i], self.d[i], self.a[i], self.alpha[i])
        return out

    def fk_flange_batch(self, Q) -> np.ndarray:
        return self.frames_batch(Q)[:, 6]

    def fk_batch(self, Q) -> np.ndarray:
        """(N, 6) joint vectors -> (N, 4, 4) base->TCP transforms."""
        return self.fk_flange_batch(Q) @ self.tcp_offset

    def fk_flange(self, q) -> np.ndarray:
        return self.fk_flange_batch(np.reshape(q, (1, 6)))[0]

    def fk(self, q) -> np.ndarray:
        """Base->TCP 4x4 transform at joint angles q."""
        return self.fk_batch(np.reshape(q, (1, 6)))[0]

    def jacobian(self, q) -> np.ndarray:
        """6x6 geometric Jacobian at the TCP, base frame: rows 0-2 linear velocity, rows 3-5 angular."""
        F = self.frames_batch(np.reshape(q, (1, 6)))[0]
        p = (F[6] @ self.tcp_offset)[:3, 3]
        z, o = F[:6, :3, 2], F[:6, :3, 3]
        return np.vstack([np.cross(z, p - o).T, z.T])

    # ---- inverse kinematics -------------------------------------------------------------------------
    def _solve(self, T, q6_hint: float) -> tuple[np.ndarray, np.ndarray, str]:
        """All 8 branches for TCP pose T; index = 4*shoulder + 2*wrist + elbow. Returns (Q, valid, why)."""
        d, a, al = self.d, self.a, self.alpha
        name = self.variant.name
        T06 = np.asarray(T, dtype=float) @ self._tcp_inv
        R, p = T06[:3, :3], T06[:3, 3]
        Q = np.full((8, 6), np.nan)
        p05 = p - d[5] * R[:, 2]  # wrist centre: the axis-5 point
        r = np.hypot(p05[0], p05[1])
        if r < d[3] - _TOL:
            return Q, np.zeros(8, bool), (
                f"the wrist centre would be {r:.3f} m from the base z axis, closer than the {name}'s shoulder "
                f"offset d4 = {d[3]:.4f} m allows; move the target away from the base axis")
        psi = np.arccos(min(d[3] / r, 1.0))
        phi = np.arctan2(p05[1], p05[0])
        L_bad = None
        for s_i, sgn1 in enumerate((1.0, -1.0)):
            q1 = phi + sgn1 * psi + np.pi / 2
            s1, c1 = np.sin(q1), np.cos(q1)
            n = np.array([s1, -c1, 0.0])  # normal of the arm plane
            c5 = R[:, 2] @ n
            x, y = R[:, 0] @ n, -(R[:, 1] @ n)
            s5abs = np.hypot(x, y)  # == sqrt(1 - c5^2), but accurate near the singularity
            for w_i, sgn5 in enumerate((1.0, -1.0)):
                q5 = np.arctan2(sgn5 * s5abs, c5)
                q6 = q6_hint if s5abs < _SINGULAR else np.arctan2(sgn5 * y, sgn5 * x)
                T01 = _dh(q1, d[0], a[0], al[0])
                T46 = _dh(q5, d[4], a[4], al[4]) @ _dh(q6, d[5], a[5], al[5])
                T14 = _inv(T01) @ T06 @ _inv(T46)
                px, py = T14[0, 3], T14[1, 3]  # frame 1's x-y plane is the arm plane
                L = np.hypot(px, py)  # shoulder joint to wrist-1 axis, in the arm plane
                c3 = (L**2 - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
                if abs(c3) > 1 + _TOL:
                    L_bad = L
                    continue
                for e_i, sgn3 in enumerate((1.0, -1.0)):
                    q3 = sgn3 * np.arccos(np.clip(c3, -1.0, 1.0))
                    q2 = np.arctan2(py, px) - np.arctan2(a[2] * np.sin(q3), a[1] + a[2] * np.cos(q3))
                    T13 = _dh(q2, d[1], a[1], al[1]) @ _dh(q3, d[2], a[2], al[2])
                    T34 = _inv(T13) @ T14
                    q4 = np.arctan2(T34[1, 0], T34[0, 0])
                    Q[4 * s_i + 2 * w_i + e_i] = wrap_angle([q1, q2, q3, q4, q5, q6])
        valid = ~np.isnan(Q).any(axis=1)
        why = ""
        if not valid.any() and L_bad is not None:
            reach, inner = abs(a[1]) + abs(a[2]), abs(abs(a[1]) - abs(a[2]))
            dist = np.linalg.norm(np.asarray(T)[:3, 3])
            side = "at most" if L_bad > reach else "at least"
            why = (f"target {dist:.3f} m from the base origin puts the wrist {L_bad:.3f} m from the shoulder "
                   f"joint; the {name}'s upper arm + forearm reach {side} "
                   f"{reach if L_bad > reach else inner:.3f} m there; "
                   + ("bring the target closer to the base" if L_bad > reach else "move the target farther out"))
        return Q, valid, why

    def ik_all(self, T, q6_hint: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """All 8 analytic IK branches of TCP pose T as ((8, 6) angles in (-pi, pi], (8,) valid mask).

        Row index = 4*shoulder + 2*wrist + elbow (0/1 each); rows for branches that do not exist are NaN.
        At a wrist singularity (sin q5 ~ 0) only q4 + q6 is defined; q6 is then set to `q6_hint`.
        """
        Q, valid, _ = self._solve(T, q6_hint)
        return Q, valid

    def ik(self, T, q_current) -> np.ndarray:
        """The valid IK solution nearest q_current (Euclidean in joint space), unwrapped within limits.

        Each joint takes the 2*pi-equivalent angle, within the variant's joint limits, nearest its current
        value, so a continuous path of poses gives a continuous joint path. Raises UnreachableError.
        """
        q_current = np.asarray(q_current, dtype=float).reshape(6)
        Q, valid, why = self._solve(T, float(q_current[5]))
        if not valid.any():
            raise UnreachableError(f"no IK solution: {why}")
        Q = Q[valid]
        k0 = np.round((q_current - Q) / (2 * np.pi))
        cand = Q[None] + 2 * np.pi * (k0[None] + np.array([-1.0, 0.0, 1.0])[:, None, None])  # (3, M, 6)
        inside = (cand >= self.lower - _TOL) & (cand <= self.upper + _TOL)
        cost = np.where(inside, np.abs(cand - q_current), np.inf)
        best = np.argmin(cost, axis=0)  # (M, 6)
        sol = np.take_along_axis(cand, best[None], axis=0)[0]
        err = np.take_along_axis(cost, best[None], axis=0)[0]
        ok = np.isfinite(err).all(axis=1)
        if not ok.any():
            raise UnreachableError(
                f"the {self.variant.name} reaches this pose in {len(Q)} configuration(s), but none within its "
                f"joint limits; choose another TCP orientation or unwind the wrist first")
        sol, err = sol[ok], err[ok]
        return np.clip(sol[np.argmin((err**2).sum(axis=1))], self.lower, self.upper)
