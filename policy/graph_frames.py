"""Frame changes in torch, for the exported graphs: policy.action_frame's numpy arithmetic, written so that it runs
inside obs_encoder.onnx (policy.action_frame stays torch-free: the bundle, and so the runtime, imports it)."""

from __future__ import annotations

import torch

from policy.config import AUX_TCP_SCALE


def rot6d_matrix(d6: torch.Tensor) -> torch.Tensor:
    """(..., 6) rot6d -> (..., 3, 3) with those columns after Gram-Schmidt (policy.action_frame.rotations)."""
    a, b = d6[..., :3], d6[..., 3:6]
    x = a / a.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = b - x * (x * b).sum(-1, keepdim=True)
    y = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    z = torch.stack([x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1], x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
                     x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]], dim=-1)
    return torch.stack([x, y, z], dim=-1)


def point_to_tcp(point: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Base-frame points (B, 3) -> the frame of `pose` (B, 9) = TCP position and rot6d: R^T (p - t)
    (policy.action_frame.points_to_tcp)."""
    R = rot6d_matrix(pose[:, 3:9])
    return torch.matmul(R.transpose(1, 2), (point - pose[:, :3]).unsqueeze(2)).squeeze(2)


def release_to_tcp(points: torch.Tensor, proprio: torch.Tensor, proprio_scale: torch.Tensor,
                   proprio_offset: torch.Tensor) -> torch.Tensor:
    """Aux points (B, >= 6) whose release point (columns 3:6) is in the base frame over AUX_TCP_SCALE -> the same
    with it relative to the gripper at the newest step of the normalized proprio (B, To, Dp), whose normalization
    (x * scale + offset, policy.normalize) is undone to read the pose in metres."""
    pose = newest_pose(proprio, proprio_scale, proprio_offset)  # first: the graphs' node order stays the shipped one
    rel = point_to_tcp(points[:, 3:6] * AUX_TCP_SCALE, pose) / AUX_TCP_SCALE
    return torch.cat([points[:, :3], rel, points[:, 6:]], dim=1)


def newest_pose(proprio: torch.Tensor, proprio_scale: torch.Tensor, proprio_offset: torch.Tensor) -> torch.Tensor:
    """(B, 9) the TCP pose (position in metres, rot6d) at the newest step of the normalized proprio (B, To, Dp),
    its normalization (x * scale + offset, policy.normalize) undone."""
    return (proprio[:, -1, :9] - proprio_offset[:9]) / proprio_scale[:9]


def with_release(points: torch.Tensor, release: torch.Tensor) -> torch.Tensor:
    """The head's points (B, >= 6; release point in the base frame over AUX_TCP_SCALE, aux_release_frame base)
    with the release point replaced where release (B, 4) = (x, y, z in metres, base frame; flag) has flag 1:
    the goal query's point (policy/goal_query.py). Flag 0 leaves the head's, bit for bit."""
    given = release[:, 3:4] > 0.5
    rel = torch.where(given, release[:, :3] / AUX_TCP_SCALE, points[:, 3:6])
    return torch.cat([points[:, :3], rel, points[:, 6:]], dim=1)


def with_grasp(points: torch.Tensor, grasp: torch.Tensor, proprio: torch.Tensor, proprio_scale: torch.Tensor,
               proprio_offset: torch.Tensor) -> torch.Tensor:
    """The head's points (B, >= 6; grasp point relative to the gripper over AUX_TCP_SCALE) with the grasp point
    replaced where grasp (B, 4) = (x, y, z in metres, base frame; flag) has flag 1, turned relative to the gripper
    at the newest step of the normalized proprio: the object query's point (policy/object_query.py). Flag 0 leaves
    the head's, bit for bit."""
    given = grasp[:, 3:4] > 0.5
    rel = point_to_tcp(grasp[:, :3], newest_pose(proprio, proprio_scale, proprio_offset)) / AUX_TCP_SCALE
    return torch.cat([torch.where(given, rel, points[:, :3]), points[:, 3:]], dim=1)
