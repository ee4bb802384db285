"""Rotations and poses in UR's conventions: rotation vectors (axis-angle, as `getActualTCPPose`), 4x4
transforms, and angle wrapping to (-pi, pi]. Plain numpy; `sim.kinematics` re-exports all of them."""

from __future__ import annotations

import numpy as np


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
