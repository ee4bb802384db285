"""Placement sampling: where the held object can be released on or in a target, and the TCP pose for it.

Targets: a container with a `{name}/inside` box site (bins, boxes, the drawer), the `table` (anywhere free in
the task area), or another object (stacking: near the centre of its top face).

A container's object is let go over its rim, near the middle, and falls in; only where nothing over the rim
is free (the drawer, under its cabinet) is it lowered to just over the cavity floor. Why: a release down in
the cavity leaves the open fingers a centimetre or two from the walls, so any policy that learns from these
demonstrations with a few centimetres of error presses a finger into a wall (the sim twin's protective stop
ended most episodes of the first distilled policies that way); over the rim the same error still drops the
object in, and the fingers never enter the container.
The object keeps its current up-axis and turns by a sampled yaw; the TCP pose follows from the grasp
transform (object in the TCP frame, measured when it was grasped), so any grasp, tilted or not, places
the object upright. Candidates must fit the region's footprint, be reachable, and leave the arm and the
held object collision-free; the gripper opening for the release is the widest that clears the walls.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from datagen.collision import Held
from sim.kinematics import UnreachableError, rotvec_to_matrix
from sim.robot import GRIPPER_MAX_DRIVER
from sim.scene import TABLE_TOP_Z, TASK_AREA

DROP = {"container": 0.015, "table": 0.006, "stack": 0.006}  # release height of the object's bottom
RIM_CLEARANCE = 0.02  # an object let go over a container's rim clears it by this much
OVER_RIM_SPREAD = 0.25  # over-the-rim releases stay within this share of the cavity's half extents
RELEASE_OPENINGS = (0.0, 0.25, 0.45)


@dataclass
class PlacePose:
    T: np.ndarray  # TCP pose at release
    T_pre: np.ndarray  # TCP pose above it, where the straight descent starts
    q: np.ndarray
    q_pre: np.ndarray
    release: float  # gripper command that lets go without touching the surroundings
    score: float


@dataclass
class Region:
    """An upward-facing rectangle: centre, in-plane axes (unit, horizontal), half extents, kind."""

    centre: np.ndarray
    axes: np.ndarray  # (2, 3)
    half: np.ndarray  # (2,)
    kind: str
    rim: float | None = None  # a container's top edge (world z)


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _upright(R: np.ndarray, max_fix: float = np.deg2rad(30)) -> np.ndarray:
    """R turned by the least rotation that makes its most vertical axis exactly vertical (objects settle
    in the hand by a few degrees; they should still land flat). Larger tilts are kept as they are."""
    k = int(np.argmax(np.abs(R[2])))
    a = R[:, k] * np.sign(R[2, k])
    angle = float(np.arccos(np.clip(a[2], -1.0, 1.0)))
    axis = np.cross(a, [0.0, 0.0, 1.0])
    if angle < 1e-9 or angle > max_fix:
        return R
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * angle) @ R


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def body_aabb(model, data, body: str) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of a body's collision geoms."""
    bid = model.body(body).id
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != bid or not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        R = data.geom_xmat[g].reshape(3, 3)
        c = data.geom_xpos[g] + R @ model.geom_aabb[g][:3]
        e = np.abs(R) @ model.geom_aabb[g][3:]
        lo, hi = np.minimum(lo, c - e), np.maximum(hi, c + e)
    return lo, hi


def target_region(model, data, target: str) -> Region:
    """The surface a target offers: a container's cavity floor, the table's task area, an object's top."""
    sid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, f"{target}/inside")
    if sid >= 0:
        R = data.site_xmat[sid].reshape(3, 3)
        half = model.site_size[sid]
        floor = data.site_xpos[sid] - R[:, 2] * half[2]
        rim = float(data.site_xpos[sid][2] + abs(R[2, 2]) * half[2])
        return Region(floor, R[:, :2].T.copy(), half[:2].copy(), "container", rim)
    if target == "table":
        (x0, x1), (y0, y1) = TASK_AREA
        return Region(np.array([(x0 + x1) / 2, (y0 + y1) / 2, TABLE_TOP_Z]), np.eye(3)[:2],
                      np.array([(x1 - x0) / 2, (y1 - y0) / 2]), "table")
    lo, hi = body_aabb(model, data, target)
    R = data.xmat[model.body(target).id].reshape(3, 3)
    yaw = np.arctan2(R[1, 0], R[0, 0])
    axes = _rz(yaw)[:, :2].T
    # Half extents of the top face along the object's own horizontal axes (its AABB is looser when yawed).
    ext = np.abs(axes @ (hi - lo)) / 2
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    return Region(centre, axes, ext * 0.3, "stack")


class PlaceSampler:
    def __init__(self, world, checker, kin, approach: float = 0.10):
        self.world, self.checker, self.kin, self.approach = world, checker, kin, approach

    def _object_corners(self, body: str) -> np.ndarray:
        """Corners of the held body's geom boxes in the body frame (for footprints)."""
        m = self.world.model
        bid = m.body(body).id
        pts = []
        for g in range(m.ngeom):
            if m.geom_bodyid[g] != bid or not (m.geom_contype[g] or m.geom_conaffinity[g]):
                continue
            c, h = m.geom_aabb[g][:3], m.geom_aabb[g][3:]
            R = np.eye(3)
            mujoco.mju_quat2Mat(R.reshape(9), m.geom_quat[g])
            signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
            pts.append(m.geom_pos[g] + (c + signs * h) @ R.T)
        return np.concatenate(pts)

    def sample(self, held: Held, target: str, q_now, rng, k: int = 3, n: int = 200,
               evaluate: int = 40) -> list[PlacePose]:
        """Up to k validated release poses for the held object on/in `target` (checker must be synced)."""
        region = target_region(self.world.model, self.world.data, target)
        heights = [] if region.rim is None else [(region.rim + RIM_CLEARANCE, OVER_RIM_SPREAD)]
        heights.append((region.centre[2] + DROP[region.kind], 1.0))
        for bottom, spread in heights:
            cands = self._candidates(held, region, q_now, rng, n, bottom, spread)
            out = self._validated(held, cands, q_now, k, evaluate)
            if out:
                return out
        return []

    def _candidates(self, held: Held, region: Region, q_now, rng, n: int, bottom: float,
                    spread: float) -> list[tuple[float, np.ndarray]]:
        """(score, TCP pose) for n sampled releases with the object's bottom at height `bottom`, within
        `spread` of the region's half extents (and inside a container's walls), lowest score first."""
        R_obj_now = _upright((self.kin.fk(q_now) @ held.T_tcp_obj)[:3, :3])
        corners = self._object_corners(held.body)
        T_obj_tcp = np.linalg.inv(held.T_tcp_obj)
        margin = 0.006  # clearance to container walls
        cands = []
        # Half the yaws square the object with the region (boxes fit bins and drawers that way), half are free.
        heading = np.arctan2(R_obj_now[1, 0], R_obj_now[0, 0])
        square = np.arctan2(region.axes[0, 1], region.axes[0, 0]) - heading
        for i in range(n):
            if i % 2:
                yaw = rng.uniform(-np.pi / 2, np.pi / 2)
            else:
                yaw = _wrap(square + rng.integers(4) * np.pi / 2 + rng.normal(0.0, 0.05))
            R = _rz(yaw) @ R_obj_now
            w = corners @ R.T  # corner offsets from the body origin, world-aligned
            uv = rng.uniform(-1.0, 1.0, 2) * region.half * spread
            xy = region.centre + uv @ region.axes
            foot = w @ region.axes.T  # corners in the region's plane coordinates
            lo_uv, hi_uv = uv + foot.min(axis=0), uv + foot.max(axis=0)
            if region.kind == "container" and (np.any(lo_uv < -region.half + margin)
                                               or np.any(hi_uv > region.half - margin)):
                continue
            T_obj = np.eye(4)
            T_obj[:3, :3] = R
            T_obj[:3, 3] = [xy[0], xy[1], bottom - w[:, 2].min()]
            score = float(np.linalg.norm(uv / np.maximum(region.half, 1e-3))) * 0.3 + 0.2 * abs(yaw) \
                + rng.uniform(0.0, 0.2)
            cands.append((score, T_obj @ T_obj_tcp))
        return sorted(cands, key=lambda c: c[0])

    def _validated(self, held: Held, cands, q_now, k: int, evaluate: int) -> list[PlacePose]:
        """The first k candidates (of the best `evaluate`) that are reachable, collision-free, and have a
        gripper opening that lets go without touching anything."""
        # The release must open the fingers clearly wider than they are around the object now.
        closure = 1.0 if held.gripper_qpos is None else float(held.gripper_qpos[0]) / GRIPPER_MAX_DRIVER
        openings = [o for o in RELEASE_OPENINGS if o < closure - 0.15] or [0.0]
        out = []
        for score, T in cands[:evaluate]:
            T_pre = T.copy()
            T_pre[2, 3] += self.approach
            try:
                q_pre = self.kin.ik(T_pre, q_now)
                q = self.kin.ik(T, q_pre)
            except UnreachableError:
                continue
            if np.max(np.abs(q - q_pre)) > 1.0:
                continue
            if not (self.checker.is_free(q, held=held) and self.checker.is_free(q_pre, held=held, clearance=0.005)):
                continue
            release = next((o for o in openings
                            if self.checker.is_free(q, gripper=o, allow=(held.body,))), None)
            if release is None:
                continue
            out.append(PlacePose(T, T_pre, q, q_pre, release, score))
            if len(out) >= k:
                break
        return out
