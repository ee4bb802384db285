"""Antipodal grasp sampling on object geometry, validated by IK, collision and a simulated close.

Why geometric sampling and not the scripted oracles' top-down-at-the-centre rule: data generation must work
for any object shape and pose and must produce varied demonstrations, so grasps are sampled on the geoms'
surfaces (ray casts against MuJoCo's primitive geoms), paired antipodally inside a friction cone, turned into
TCP poses (fingers close along the tool x axis, approach along tool z, tilted around the vertical), and kept
only if the arm reaches them, the open gripper fits, and a physics close in a scratch copy really holds.
Handles (capsule or box bars on articulated parts) are sampled along their long axis the same way.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import mujoco
import numpy as np

from datagen.collision import Held, gripper_table
from sim.kinematics import UnreachableError
from sim.robot import GRIPPER_PAD_GEOMS, GRIPPER_STROKE

FRICTION_CONE = np.deg2rad(15.0)  # half-angle kept well inside atan(mu ~ 0.9) for a margin on pose error
MAX_WIDTH = GRIPPER_STROKE - 0.008  # the open fingers must clear the object by a few millimetres
PAD_CENTRE = 0.014  # m: the pads' centre sits this far behind the TCP (fingertips) along the approach axis
CLOSE_SECONDS = 0.3


@dataclass
class Grasp:
    T: np.ndarray  # TCP pose at the grasp
    T_pre: np.ndarray  # TCP pose before the straight approach
    q: np.ndarray
    q_pre: np.ndarray
    width: float
    score: float  # lower is better
    opening: float  # gripper command while approaching (0 = fully open)
    held: Held | None = None  # after the simulated close: object in the TCP frame + gripper angles


def _geom_ids(model, body: str) -> list[int]:
    bid = model.body(body).id
    return [g for g in range(model.ngeom) if model.geom_bodyid[g] == bid and
            (model.geom_contype[g] or model.geom_conaffinity[g])]


def ray_geoms(model, data, geoms, pnt, vec) -> tuple[float, np.ndarray]:
    """Nearest hit of the ray pnt + x·vec (x >= 0) on `geoms`: (distance or -1, outward unit normal)."""
    best, normal = -1.0, np.zeros(3)
    n = np.zeros(3)
    for g in geoms:
        x = mujoco.mju_rayGeom(data.geom_xpos[g], data.geom_xmat[g], model.geom_size[g], pnt, vec,
                               int(model.geom_type[g]), n)
        if x >= 0 and (best < 0 or x < best):
            best, normal = x, n.copy()
    return best, normal


def surface_points(model, data, geoms, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """~n points with outward normals on the geoms, from rays aimed at random points inside them."""
    pts, nrm = [], []
    for _ in range(n):
        g = geoms[int(rng.integers(len(geoms)))]
        R = data.geom_xmat[g].reshape(3, 3)
        half = model.geom_aabb[g][3:]
        target = data.geom_xpos[g] + R @ (model.geom_aabb[g][:3] + rng.uniform(-0.6, 0.6, 3) * half)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        start = target + d * 2.0 * float(model.geom_rbound[g] + 0.01)
        x, normal = ray_geoms(model, data, geoms, start, -d)
        if x >= 0:
            pts.append(start - d * x)
            nrm.append(normal)
    return np.array(pts).reshape(-1, 3), np.array(nrm).reshape(-1, 3)


def _cone_dir(axis, max_angle, rng) -> np.ndarray:
    """A random unit vector within `max_angle` of `axis`."""
    perp = np.cross(axis, rng.normal(size=3))
    perp /= np.linalg.norm(perp) + 1e-12
    a = rng.uniform(0.0, max_angle)
    return np.cos(a) * axis + np.sin(a) * perp


def antipodal_pairs(model, data, geoms, n: int, rng, cone: float = FRICTION_CONE, max_width: float = MAX_WIDTH):
    """(p1, p2, closing direction, width) for point pairs whose normals lie inside the friction cone."""
    pts, nrm = surface_points(model, data, geoms, n, rng)
    reach = 2.0 * max(float(model.geom_rbound[g]) for g in geoms) + 0.05
    out = []
    for p1, n1 in zip(pts, nrm):
        # Closing direction, from p1 through the object. Flat pads turn a face flush with them as they
        # close, so directions stay near the normal; the friction cone is then checked at both contacts.
        d = _cone_dir(-n1, min(cone, np.deg2rad(4.0)), rng)
        x, n2 = ray_geoms(model, data, geoms, p1 + d * reach, -d)
        if x < 0:
            continue
        p2 = p1 + d * (reach - x)
        width = float(np.dot(p2 - p1, d))
        if not 1e-3 < width < max_width:
            continue
        if np.dot(-n1, d) < np.cos(cone) or np.dot(n2, d) < np.cos(cone):
            continue
        out.append((p1, p2, d, width))
    return out


def tcp_frame(x_close, approach_hint, tilt: float) -> np.ndarray | None:
    """Rotation with tool x = closing axis, tool z = approach hint made orthogonal, tilted about x."""
    x = x_close / np.linalg.norm(x_close)
    z = approach_hint - np.dot(approach_hint, x) * x
    if np.linalg.norm(z) < 0.5:  # closing axis too close to the approach: no such grasp from above
        return None
    z /= np.linalg.norm(z)
    z = np.cos(tilt) * z + np.sin(tilt) * np.cross(x, z)
    return np.column_stack([x, np.cross(z, x), z])


TURN_COST = 0.2  # per radian of wrist turn to the grasp: 90 degrees weigh as much as 1.6 cm of lateral offset


def _best_flip(R: np.ndarray, R_now: np.ndarray) -> np.ndarray:
    """The 2F-85 is symmetric about its approach axis: take the half-turn variant nearer the current wrist."""
    flipped = R @ np.diag([-1.0, -1.0, 1.0])
    return R if np.trace(R_now.T @ R) >= np.trace(R_now.T @ flipped) else flipped


def simulate_close(world, q, body: str, opening: float, touch_geoms=None, seconds: float = CLOSE_SECONDS,
                   max_turn: float = np.deg2rad(6.0)):
    """Close the gripper at arm configuration q in a scratch copy of the live state; Held if both pads touch.

    `touch_geoms` (ids) are what the pads must touch (default: the body's geoms); the object must not be
    knocked more than 2 cm nor turned more than `max_turn`.
    """
    m = world.model
    d = copy.copy(world.data)
    gadr = np.array([m.jnt_qposadr[j] for j in range(m.njnt) if m.joint(j).name.startswith("gripper/")])
    table = gripper_table(world, gadr)
    d.qpos[world.arm_qpos_adr] = q
    d.qpos[gadr] = [np.interp(opening, np.linspace(0, 1, len(table)), col) for col in table.T]
    d.qvel[:] = 0.0
    d.ctrl[world.arm_actuators] = q
    d.ctrl[world.gripper_actuator] = 255.0
    mujoco.mj_forward(m, d)
    bid = m.body(body).id
    start, R0 = d.xpos[bid].copy(), d.xmat[bid].reshape(3, 3).copy()
    mujoco.mj_step(m, d, nstep=int(round(seconds / m.opt.timestep)))
    mujoco.mj_forward(m, d)
    want = set(_geom_ids(m, body) if touch_geoms is None else touch_geoms)
    pads = {m.geom(n).id: ("left" if "left" in n else "right") for n in GRIPPER_PAD_GEOMS}
    sides = set()
    for i in range(d.ncon):
        g1, g2 = d.contact.geom1[i], d.contact.geom2[i]
        for pad, other in ((g1, g2), (g2, g1)):
            if pad in pads and other in want:
                sides.add(pads[pad])
    # The 2F-85's fingertips give way on an edge contact, twisting the object in the hand: such grasps
    # would place it crooked, so the object may shift but hardly turn while the fingers close.
    turn = np.arccos(np.clip((np.trace(R0.T @ d.xmat[bid].reshape(3, 3)) - 1) / 2, -1.0, 1.0))
    if len(sides) < 2 or np.linalg.norm(d.xpos[bid] - start) > 0.02 or turn > max_turn:
        return None
    T_tcp = np.eye(4)
    T_tcp[:3, :3] = d.site_xmat[world.tcp_site].reshape(3, 3)
    T_tcp[:3, 3] = d.site_xpos[world.tcp_site]
    T_obj = np.eye(4)
    T_obj[:3, :3] = d.xmat[bid].reshape(3, 3)
    T_obj[:3, 3] = d.xpos[bid]
    return Held(body, np.linalg.inv(T_tcp) @ T_obj, d.qpos[gadr].copy())


class GraspSampler:
    """Samples and validates grasps for one world; `checker` must be synced to the live state."""

    def __init__(self, world, checker, kin, approach: float = 0.10, max_tilt: float = np.deg2rad(25)):
        self.world, self.checker, self.kin = world, checker, kin
        self.approach, self.max_tilt = approach, max_tilt

    def _max_depth(self, c, R) -> float:
        """How far past the contact centre c the TCP may go along the approach and keep the safety
        workspace's finger points above the table (the runtime filter would stop the arm lower down)."""
        ws = self.checker.workspace
        if ws is None or R[2, 2] > -1e-3:
            return np.inf
        lowest = c[2] + float(np.min(ws.points @ R[2])) if len(ws.points) else c[2]
        return (lowest - ws.floor - 1e-3) / -R[2, 2]  # 1 mm to spare for the line's round-off

    def _validate(self, cands, q_now, body, k, openings=(0.0,), touch=None, evaluate=40) -> list[Grasp]:
        """IK, open-gripper collision at pre-grasp and grasp, then the simulated close, best score first."""
        out: list[Grasp] = []
        for score, T, width in sorted(cands, key=lambda c: c[0])[:evaluate]:
            T_pre = T.copy()
            T_pre[:3, 3] -= self.approach * T[:3, 2]
            try:
                q_pre = self.kin.ik(T_pre, q_now)
                q = self.kin.ik(T, q_pre)
            except UnreachableError:
                continue
            if np.max(np.abs(q - q_pre)) > 1.0:  # another IK branch: no straight approach between them
                continue
            for opening in openings:
                if self.checker.is_free(q, gripper=opening) and \
                        self.checker.is_free(q_pre, gripper=opening, clearance=0.005):
                    held = simulate_close(self.world, q, body, opening, touch)
                    # The closed fingers swing towards the tips: they must still clear the surroundings.
                    if held is not None and self.checker.is_free(q, gripper=held.gripper_qpos, allow=(body,)):
                        out.append(Grasp(T, T_pre, q, q_pre, width, score, opening, held))
                    break
            if len(out) >= k:
                break
        return out

    def object_grasps(self, body: str, q_now, rng, k: int = 3, n: int = 120) -> list[Grasp]:
        """Up to k validated grasps of a free body, preferring upright approaches near its centre."""
        m, d = self.world.model, self.world.data
        geoms = _geom_ids(m, body)
        centre = d.xipos[m.body(body).id]
        R_now = self.kin.fk(q_now)[:3, :3]
        down = np.array([0.0, 0.0, -1.0])
        cands = []
        for p1, p2, x, width in antipodal_pairs(m, d, geoms, n, rng):
            tilt = rng.uniform(-self.max_tilt, self.max_tilt)
            R = tcp_frame(x, down, tilt)
            if R is None:
                continue
            R = _best_flip(R, R_now)
            c = 0.5 * (p1 + p2)
            depth = min(rng.uniform(0.0, PAD_CENTRE), self._max_depth(c, R))
            if depth < -0.003:  # the pads would no longer reach the contacts
                continue
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = c + R[:, 2] * depth
            # Gravity pivots the object about the closing axis by its centre's horizontal offset from it:
            # that offset costs most; height on the object matters less; tilt away from vertical a little.
            v = centre - c
            v -= np.dot(v, x) * x
            lateral, vertical = np.linalg.norm(v[:2]), abs(v[2])
            upright = np.arccos(np.clip(-R[2, 2], -1, 1))
            # Among equally good grasps (a block's two face pairs, a cylinder's any direction) prefer the least
            # wrist turn: the data then holds one grasp yaw per situation, not a uniform spread a distilled
            # policy must learn as a multimodal target (and the arm moves less).
            turn = np.arccos(np.clip((np.trace(R_now.T @ R) - 1.0) / 2.0, -1.0, 1.0))
            cands.append((upright + 20.0 * lateral + 4.0 * vertical + TURN_COST * turn + rng.uniform(0.0, 0.1),
                          T, width))
        return self._validate(cands, q_now, body, k)

    def handle_grasps(self, geom: str, q_now, rng, k: int = 3, n: int = 40,
                      openings=(0.5, 0.3, 0.65), front: bool = False) -> list[Grasp]:
        """Grasps around a bar handle (capsule or box geom): approach across the bar, fingers around it; from
        above (the fingers closing horizontally) or with `front` from the robot's side, level, the fingers
        closing above and below the bar, so the gripper's outer links stay clear of what the bar stands off."""
        m, d = self.world.model, self.world.data
        g = m.geom(geom).id
        R_g = d.geom_xmat[g].reshape(3, 3)
        size = m.geom_size[g]
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            axis, half = R_g[:, 2], float(size[1])
        else:
            i = int(np.argmax(size[:3]))
            axis, half = R_g[:, i], float(size[i])
        body = m.body(m.geom_bodyid[g]).name
        R_now = self.kin.fk(q_now)[:3, :3]
        approach = np.array([0.0, 0.0, -1.0])
        if front:  # level, across the bar, away from the robot's base (the world origin)
            approach = np.cross(axis, [0.0, 0.0, 1.0])
            approach *= np.sign(np.dot(approach[:2], d.geom_xpos[g][:2])) / np.linalg.norm(approach)
        cands = []
        for _ in range(n):
            t = rng.uniform(-0.5, 0.5) * max(half - 0.015, 0.0)
            z = approach - np.dot(approach, axis) * axis
            x = np.cross(axis, z / np.linalg.norm(z))
            tilt = rng.uniform(-0.5, 0.5) * self.max_tilt
            R = tcp_frame(x, approach, tilt)
            if R is None:
                continue
            R = _best_flip(R, R_now)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = d.geom_xpos[g] + t * axis + R[:, 2] * rng.uniform(0.0, 0.006)
            cands.append((abs(tilt) + 5.0 * abs(t) + rng.uniform(0.0, 0.1), T, 2.0 * float(size[0])))
        return self._validate(cands, q_now, body, k, openings=openings, touch={g})
