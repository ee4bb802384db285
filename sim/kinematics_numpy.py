"""The batched numpy forms of the UR kinematics: the base class of `sim.kinematics.Kinematics`.

`frames_batch` / `fk_flange_batch` / `fk_batch` evaluate the standard-DH chain T_i = Rz(q_i) Tz(d_i) Tx(a_i)
Rx(alpha_i) on any number of configurations at once with numpy 4x4 products; `_solve_numpy` is the reference
all-branch analytic IK in the same style. `Kinematics` answers single configurations in scalar math (~10x
faster) and falls back to these for non-finite input or a chain without the UR structure; tests hold the two
together.
"""

from __future__ import annotations

import numpy as np

from sim.robot import RobotVariant, get_variant
from sim.rotations import wrap_angle

SINGULAR = 1e-10  # |sin q5| below this: wrist axes 4 and 6 align, q4 + q6 is all that is defined
TOL = 1e-9  # slack on acos arguments and joint limits for targets exactly on a boundary


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


class NumpyKinematics:
    """Batched FK and the reference IK of one UR variant with a fixed flange->TCP transform."""

    def __init__(self, variant: RobotVariant | str = "ur5e", tcp_offset=None):
        self.variant = get_variant(variant) if isinstance(variant, str) else variant
        v = self.variant
        self.d, self.a, self.alpha = v.dh_d, v.dh_a, v.dh_alpha
        self.tcp_offset = np.eye(4) if tcp_offset is None else np.asarray(tcp_offset, dtype=float).copy()
        self._tcp_inv = _inv(self.tcp_offset)
        self.lower, self.upper = np.array(v.joint_lower), np.array(v.joint_upper)

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

    def _solve_numpy(self, T, q6_hint: float) -> tuple[np.ndarray, np.ndarray, str]:
        """All 8 branches for TCP pose T; index = 4*shoulder + 2*wrist + elbow. Returns (Q, valid, why).

        The reference implementation with numpy 4x4 products: `Kinematics._solve` computes the same in scalar
        math (~10x faster) and falls back to this one for non-finite input; tests hold the two together.
        """
        d, a, al = self.d, self.a, self.alpha
        name = self.variant.name
        T06 = np.asarray(T, dtype=float) @ self._tcp_inv
        R, p = T06[:3, :3], T06[:3, 3]
        Q = np.full((8, 6), np.nan)
        p05 = p - d[5] * R[:, 2]  # wrist centre: the axis-5 point
        r = np.hypot(p05[0], p05[1])
        if r < d[3] - TOL:
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
                q6 = q6_hint if s5abs < SINGULAR else np.arctan2(sgn5 * y, sgn5 * x)
                T01 = _dh(q1, d[0], a[0], al[0])
                T46 = _dh(q5, d[4], a[4], al[4]) @ _dh(q6, d[5], a[5], al[5])
                T14 = _inv(T01) @ T06 @ _inv(T46)
                px, py = T14[0, 3], T14[1, 3]  # frame 1's x-y plane is the arm plane
                L = np.hypot(px, py)  # shoulder joint to wrist-1 axis, in the arm plane
                c3 = (L**2 - a[1] ** 2 - a[2] ** 2) / (2 * a[1] * a[2])
                if abs(c3) > 1 + TOL:
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
