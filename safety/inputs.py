"""Input validation for the filter: joint vectors and TCP poses, rejected (None) when malformed."""

from __future__ import annotations

import math

import numpy as np

ROT_TOL = 1e-6  # orthonormality tolerance of a rotation matrix / unit quaternion in a TCP target


def vec6(x):
    """6 finite floats as a list, or None (wrong shape, NaN/Inf, not numbers)."""
    try:
        if type(x) is np.ndarray:
            if x.shape != (6,) or x.dtype.kind != "f":
                if x.shape != (6,) or x.dtype.kind not in "iu":
                    return None
                x = x.astype(float)
            vals = x.tolist()
        else:
            vals = list(x)
            if len(vals) != 6:
                return None
            vals = [float(e) for e in vals]
    except (TypeError, ValueError):
        return None
    return vals if all(map(math.isfinite, vals)) else None


def parse_pose(x):
    """((px, py, pz), R row-major 9-tuple) from a 4x4 transform, a UR pose [x y z rx ry rz] or
    [x y z qw qx qy qz]; None when malformed (NaN/Inf, wrong shape, non-unit rotation or quaternion)."""
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        return None
    if not np.all(np.isfinite(arr)):
        return None
    if arr.shape == (4, 4):
        R = arr[:3, :3]
        if np.abs(arr[3] - (0.0, 0.0, 0.0, 1.0)).max() > ROT_TOL:
            return None
        if np.abs(R.T @ R - np.eye(3)).max() > ROT_TOL or np.linalg.det(R) <= 0.0:
            return None
        return tuple(arr[:3, 3].tolist()), tuple(R.ravel().tolist())
    if arr.shape == (6,):
        from sim.rotations import rotvec_to_matrix

        return tuple(arr[:3].tolist()), tuple(rotvec_to_matrix(arr[3:]).ravel().tolist())
    if arr.shape == (7,):
        w, xq, yq, zq = arr[3:].tolist()
        n = w * w + xq * xq + yq * yq + zq * zq
        if abs(n - 1.0) > ROT_TOL:
            return None
        R = (1 - 2 * (yq * yq + zq * zq), 2 * (xq * yq - zq * w), 2 * (xq * zq + yq * w),
             2 * (xq * yq + zq * w), 1 - 2 * (xq * xq + zq * zq), 2 * (yq * zq - xq * w),
             2 * (xq * zq - yq * w), 2 * (yq * zq + xq * w), 1 - 2 * (xq * xq + yq * yq))
        return tuple(arr[:3].tolist()), R
    return None


__all__ = ["vec6", "parse_pose", "ROT_TOL"]
