"""Collision guard on the MuJoCo model: self-collision, the table and keep-out boxes, as a speed scale.

The model is the arm with its 2F-85 (`sim.robot.robot_spec`), the table (`sim.scene`'s box, top moved to the
limits' table plane) and every keep-out box as a world geom. Only collision geoms count (the meshes' convex
collision shapes and primitives). Pairs left out: bodies next to each other in the chain (the gripper
counts as part of wrist 3), the gripper's own parts, the wrist 1 and wrist 3 links (the wrist's geometry
keeps them 2 cm apart at the closest), the shoulder against the table (it only turns about
the base axis, its clearance never changes), the fingers against the table (the filter's finger points
keep them above it, and grasping needs them close), and pairs that are never farther apart than
`slow_distance` anywhere in the joint range (structural neighbours, found by sampling at build time).

The fingers are placed for the least closure they can have until the next gripper command (`set_closure`, from
the controller through the filter; open until told), as the workspace's finger points are: a closed hand
pushing a drawer shut keeps its fingers' real distance from the cabinet's top, not an open hand's.

`check(q_now, q_pred)` measures the smallest clearance at the current command and at the predicted pose
(the command plus the motion until the next check plus its braking travel) and returns a scale in [0, 1]:
1 beyond slow_distance, a linear ramp down to 0 at stop_distance. A prediction that is clearer than now
(moving away) gets 1, so the arm can always leave a tight spot. Like MoveIt Servo's check it runs at a lower
rate than the control loop; the filter holds the last scale in between.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import mujoco
import numpy as np

from safety.workspace import clip_closure

_CHAIN = ("shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link")
_FINGER_PARTS = ("driver", "coupler", "spring_link", "follower", "pad")
TABLE_GEOM = "safety/table"


@dataclass(frozen=True)
class CollisionCheck:
    scale: float
    clearance_now: float
    clearance_pred: float
    pair: tuple[str, str] | None  # the closest pair at the predicted pose


class CollisionGuard:
    def __init__(self, limits, samples: int = 300, seed: int = 0):
        from sim.robot import ARM_JOINTS, GRIPPER_PREFIX, get_variant, robot_spec
        from sim.scene import TABLE_CENTRE, TABLE_HALF

        cfg = limits.collision
        self.slow = float(cfg.slow_distance)
        self.stop = float(cfg.stop_distance)
        variant = get_variant(limits.variant)
        spec = robot_spec(variant)
        tx, ty = TABLE_CENTRE
        z_top = float(limits.workspace.table_z)
        spec.worldbody.add_geom(name=TABLE_GEOM, type=mujoco.mjtGeom.mjGEOM_BOX, size=list(TABLE_HALF),
                                pos=[tx, ty, z_top - TABLE_HALF[2]])
        self.obstacles = [TABLE_GEOM]
        for k, b in enumerate(limits.workspace.keepout):
            name = f"safety/keepout{k}"
            half = [(b[i + 3] - b[i]) / 2 for i in range(3)]
            centre = [(b[i + 3] + b[i]) / 2 for i in range(3)]
            spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=centre)
            self.obstacles.append(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            self.model = m = spec.compile()
        self.data = mujoco.MjData(m)
        self._qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in ARM_JOINTS])
        self._closures, angles, names = finger_sweep(variant.name)
        self._finger_adr = np.array([m.jnt_qposadr[m.joint(n).id] for n in names], dtype=int)
        self._finger_angles = angles
        self.closure = 0.0
        self._finger_q = angles[0].copy()

        def link(g):  # chain index 1..6; the gripper is part of wrist 3 (6); world 0
            body = m.body(m.geom_bodyid[g]).name
            if body in _CHAIN:
                return _CHAIN.index(body) + 1
            return 6 if body.startswith(GRIPPER_PREFIX) else 0

        def label(g):
            return m.geom(g).name or m.body(m.geom_bodyid[g]).name

        def is_gripper(g):
            return m.body(m.geom_bodyid[g]).name.startswith(GRIPPER_PREFIX)

        def is_finger(g):
            body = m.body(m.geom_bodyid[g]).name
            return body.startswith(GRIPPER_PREFIX) and any(p in body for p in _FINGER_PARTS)

        robot = [g for g in range(m.ngeom) if (m.geom_contype[g] or m.geom_conaffinity[g]) and link(g) > 0]
        obst = [m.geom(n).id for n in self.obstacles]
        pairs = []
        for o in obst:
            for g in robot:
                if link(g) == 1 and o == obst[0]:
                    continue  # shoulder vs table: constant clearance
                if is_finger(g) and o == obst[0]:
                    continue  # fingers vs table: the filter's finger points handle it
                pairs.append((g, o))
        self_pairs = []
        if cfg.self_collision:
            for i, a in enumerate(robot):
                for b in robot[i + 1:]:
                    la, lb = link(a), link(b)
                    if abs(la - lb) < 2 or {la, lb} == {4, 6} and not (is_gripper(a) or is_gripper(b)):
                        continue  # neighbours; wrist 1 and wrist 3 cannot meet (2 cm apart at the closest)
                    self_pairs.append((a, b))
        self_pairs = self._drop_structural(self_pairs, variant, samples, seed)
        pairs += self_pairs
        self.pairs = np.array(pairs, dtype=int).reshape(-1, 2)
        self.labels = [(label(a), label(b)) for a, b in self.pairs]
        self._rb = m.geom_rbound[self.pairs[:, 0]] + m.geom_rbound[self.pairs[:, 1]]
        self._world_box = np.array([m.geom_bodyid[b] == 0 and m.geom_type[b] == mujoco.mjtGeom.mjGEOM_BOX
                                    for b in self.pairs[:, 1]])

    def _drop_structural(self, pairs, variant, samples, seed):
        if not pairs:
            return pairs
        m, d = self.model, self.data
        rng = np.random.default_rng(seed)
        lo, hi = np.array(variant.joint_lower), np.array(variant.joint_upper)
        far = np.zeros(len(pairs), bool)
        for q in rng.uniform(lo, hi, size=(samples, 6)):
            d.qpos[self._qadr] = q
            mujoco.mj_kinematics(m, d)
            for k, (a, b) in enumerate(pairs):
                if not far[k] and mujoco.mj_geomDistance(m, d, int(a), int(b), self.slow, None) >= self.slow:
                    far[k] = True
            if far.all():
                break
        return [p for p, f in zip(pairs, far) if f]

    # ---- the fingers ----------------------------------------------------------------------------------
    def set_closure(self, closure: float) -> None:
        """Place the fingers for this closure (0 open .. 1 closed; clipped, not a number: open)."""
        c = clip_closure(closure)
        if c != self.closure:
            self.closure = c
            self._finger_q = np.array([np.interp(c, self._closures, a) for a in self._finger_angles.T])

    # ---- queries --------------------------------------------------------------------------------------
    def clearance(self, q) -> tuple[float, int]:
        """Smallest distance (capped at slow_distance) over the checked pairs at joints q, and its pair index."""
        m, d = self.model, self.data
        d.qpos[self._qadr] = q
        d.qpos[self._finger_adr] = self._finger_q
        mujoco.mj_kinematics(m, d)
        a, b = self.pairs[:, 0], self.pairs[:, 1]
        pa, pb = d.geom_xpos[a], d.geom_xpos[b]
        centre = np.linalg.norm(pa - pb, axis=1) - self._rb
        if self._world_box.any():  # world boxes: distance from the robot geom's sphere to the box itself
            wb = self._world_box
            size = m.geom_size[b[wb]]
            gap = np.maximum(np.abs(pa[wb] - pb[wb]) - size, 0.0)
            centre[wb] = np.linalg.norm(gap, axis=1) - m.geom_rbound[a[wb]]
        near = np.flatnonzero(centre < self.slow)
        best, arg = self.slow, -1
        for k in near:
            dist = mujoco.mj_geomDistance(m, d, int(a[k]), int(b[k]), best, None)
            if dist < best:
                best, arg = dist, int(k)
        return float(best), arg

    def scale_for(self, clearance: float) -> float:
        if clearance >= self.slow:
            return 1.0
        if clearance <= self.stop:
            return 0.0
        return (clearance - self.stop) / (self.slow - self.stop)

    def check(self, q_now, q_pred) -> CollisionCheck:
        now, _ = self.clearance(q_now)
        pred, arg = self.clearance(q_pred)
        scale = 1.0 if pred > now else self.scale_for(pred)
        pair = self.labels[arg] if arg >= 0 else None
        return CollisionCheck(scale, now, pred, pair)


@functools.lru_cache(maxsize=2)
def finger_sweep(variant: str, steps: int = 1500, every: int = 10):
    """(closures, joint angles [n, joints], joint names): the gripper's joints as it closes slowly on nothing in
    sim.robot's model, sampled every `every` steps; closures as the sim gripper measures them, increasing.
    Why a sweep: the 2F-85's linkage is closed by equality constraints, so its joints cannot be set from the
    driver's angle alone; once per process (~0.2 s)."""
    from sim.robot import GRIPPER_DRIVER_JOINTS, GRIPPER_MAX_DRIVER, GRIPPER_PREFIX, get_variant, robot_spec

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        m = robot_spec(get_variant(variant)).compile()
    d = mujoco.MjData(m)
    names = tuple(m.joint(j).name for j in range(m.njnt) if m.joint(j).name.startswith(GRIPPER_PREFIX))
    adr = np.array([m.jnt_qposadr[m.joint(n).id] for n in names])
    drivers = np.array([m.jnt_qposadr[m.joint(n).id] for n in GRIPPER_DRIVER_JOINTS])
    lo, hi = m.actuator_ctrlrange[-1]
    closures, angles = [], []
    for k in range(steps + 1):
        d.ctrl[-1] = lo + (hi - lo) * min(1.0, k / (0.8 * steps))
        mujoco.mj_step(m, d)
        if k % every == 0:
            c = float(np.clip(d.qpos[drivers].mean() / GRIPPER_MAX_DRIVER, 0.0, 1.0))
            if not closures or c > closures[-1]:
                closures.append(c)
                angles.append(d.qpos[adr].copy())
    closures[0], closures[-1] = 0.0, max(1.0, closures[-1])  # the ends: open and closed
    return np.array(closures), np.array(angles), names


__all__ = ["CollisionGuard", "CollisionCheck", "TABLE_GEOM", "finger_sweep"]
