"""Actions relative to the gripper (`action_frame = "tcp"`), and back to the absolute targets the robot takes.

The recorded action is an absolute end-effector target in the robot base frame. With `action_frame = "tcp"`
the policy instead learns each chunk in the frame of the gripper at the chunk's "now" observation: position
R_now^T (p - p_now), rotation R_now^T R, gripper unchanged (UMI's relative trajectories). What the wrist
camera shows (the object 6 cm ahead and 2 cm left) then maps to the same numbers in every scene, where an
absolute target has to be worked out from where the robot and the scene camera happen to be. The bundle
composes the chunk with the TCP pose in the newest proprio row, so the runtime always receives absolute
targets, whichever frame a policy was trained in.

numpy only: the runtime's inference path (policy.bundle) uses it and never imports torch.
Layouts (datagen.schema): action = pos 3 | rot6d 6 | gripper 1; proprio starts with TCP pos 3 | rot6d 6.
"""

from __future__ import annotations

import numpy as np

FRAMES = ("base", "tcp")


def rotations(d6: np.ndarray) -> np.ndarray:
    """(..., 6) rot6d (the first two columns, Gram-Schmidt on the way) -> (..., 3, 3)."""
    d6 = np.asarray(d6, np.float64)
    # written out rather than np.linalg.norm / np.cross: the same arithmetic, but those wrappers' axis
    # handling was two thirds of a training sample's assembly time (called per sample, on a few rows)
    a = d6[..., :3]
    x = a / np.maximum(np.sqrt((a * a).sum(-1, keepdims=True)), 1e-12)
    b = d6[..., 3:6] - x * (x * d6[..., 3:6]).sum(-1, keepdims=True)
    y = b / np.maximum(np.sqrt((b * b).sum(-1, keepdims=True)), 1e-12)
    R = np.empty(d6.shape[:-1] + (3, 3))
    R[..., 0], R[..., 1] = x, y
    R[..., 0, 2] = x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1]
    R[..., 1, 2] = x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2]
    R[..., 2, 2] = x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]
    return R


def rot6d_of(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): first column then second column."""
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def orthonormalize_rot6d(actions: np.ndarray, rot: slice = slice(3, 9)) -> np.ndarray:
    """Gram-Schmidt on the two rotation columns of every action (..., Da), in float32: a valid rotation for
    the robot from a network's raw output (used by the torch reference and by the bundle alike)."""
    out = np.array(actions, dtype=np.float32, copy=True)
    a, b = out[..., rot.start:rot.start + 3], out[..., rot.start + 3:rot.stop]
    x = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-8)
    b = b - x * (x * b).sum(-1, keepdims=True)
    y = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-8)
    out[..., rot] = np.concatenate([x, y], axis=-1)
    return out


def points_to_tcp(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Base-frame points (..., N, 3) -> the frame of `pose` (..., 9): R^T (p - p_tcp), float64."""
    p0, R0 = np.asarray(pose, np.float64)[..., None, :3], rotations(np.asarray(pose)[..., 3:9])[..., None, :, :]
    return np.einsum("...ji,...j->...i", R0, np.asarray(points, np.float64) - p0)


def points_from_tcp(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The inverse of points_to_tcp: points (..., N, 3) in the frame of `pose` (..., 9) -> base frame, float64."""
    p0, R0 = np.asarray(pose, np.float64)[..., None, :3], rotations(np.asarray(pose)[..., 3:9])[..., None, :, :]
    return p0 + np.einsum("...ij,...j->...i", R0, np.asarray(points, np.float64))


def to_tcp(actions: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Absolute actions (..., N, Da) -> relative to `pose` (..., 9) = TCP position and rot6d (one per chunk)."""
    a = np.asarray(actions, np.float64)
    R0 = rotations(np.asarray(pose)[..., 3:9])[..., None, :, :]
    out = a.copy()
    out[..., :3] = points_to_tcp(a[..., :3], pose)
    out[..., 3:9] = rot6d_of(np.swapaxes(R0, -1, -2) @ rotations(a[..., 3:9]))
    return out.astype(np.float32)


def from_tcp(actions: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """The inverse of `to_tcp`: relative actions (..., N, Da) and the pose they are relative to -> absolute."""
    a = np.asarray(actions, np.float64)
    p0, R0 = np.asarray(pose, np.float64)[..., None, :3], rotations(np.asarray(pose)[..., 3:9])[..., None, :, :]
    out = a.copy()
    out[..., :3] = p0 + np.einsum("...ij,...j->...i", R0, a[..., :3])
    out[..., 3:9] = rot6d_of(R0 @ rotations(a[..., 3:9]))
    return out.astype(np.float32)


def window_indices(length: int, obs_horizon: int, pred_horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """For every "now" step n of an episode of `length`: (now (length,), action steps (length, Tp)) of the
    window whose newest observation is n, clamped to the episode as policy.data's sampler does."""
    now = np.arange(length)
    steps = np.clip(now[:, None] - (obs_horizon - 1) + np.arange(pred_horizon)[None], 0, length - 1)
    return now, steps


def relative_windows(action: np.ndarray, proprio: np.ndarray, obs_horizon: int, pred_horizon: int) -> np.ndarray:
    """Every window's chunk in its own "now" TCP frame: (T, Da), (T, Dp) -> (T * Tp, Da), for fitting stats."""
    now, steps = window_indices(len(action), obs_horizon, pred_horizon)
    return to_tcp(np.asarray(action)[steps], np.asarray(proprio)[now, :9]).reshape(-1, action.shape[1])
