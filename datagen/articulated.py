"""Opening and closing articulated parts: grasp the handle, move it along the joint, release, retreat.

Works from the model alone: the joint's type, range, axis and anchor come from MuJoCo, the handle is the
most elongated capsule/box geom named "*handle*" in the moving body's subtree. A slide joint is driven by a
straight TCP line along its axis; a hinge by an arc of TCP poses about its axis (the grasp rigidly rotates
with the part). While the part moves with the hand, contacts with the moving part are allowed; everything
else (the carcass, other objects, the table) is still checked.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from datagen.motion import PlanningFailed
from datagen.trajectory import Motion, Segment
from sim.kinematics import rotvec_to_matrix

OPEN_TARGET, CLOSED_TARGET = 0.95, 0.03  # fractions of the joint range the primitives drive to
GRASP_SECONDS, RELEASE_SECONDS = 0.5, 0.4
RETREAT = 0.08


@dataclass
class JointInfo:
    name: str
    kind: str  # "slide" or "hinge"
    qpos_adr: int
    lo: float
    hi: float
    body: str  # the moving body
    axis: np.ndarray  # world frame
    anchor: np.ndarray  # world frame point on the axis

    def fraction(self, data) -> float:
        return (float(data.qpos[self.qpos_adr]) - self.lo) / (self.hi - self.lo)


def joint_info(world, joint: str) -> JointInfo:
    m, d = world.model, world.data
    try:
        j = m.joint(joint).id
    except KeyError:
        raise KeyError(f"no joint named {joint!r}") from None
    kinds = {int(mujoco.mjtJoint.mjJNT_SLIDE): "slide", int(mujoco.mjtJoint.mjJNT_HINGE): "hinge"}
    if int(m.jnt_type[j]) not in kinds:
        raise ValueError(f"joint {joint!r} is neither a slide nor a hinge")
    b = m.jnt_bodyid[j]
    lo, hi = m.jnt_range[j]
    return JointInfo(joint, kinds[int(m.jnt_type[j])], int(m.jnt_qposadr[j]), float(lo), float(hi), m.body(b).name,
                     d.xaxis[j].copy(), d.xanchor[j].copy())


def find_handle(world, body: str) -> str:
    """The handle geom of a moving part: the longest capsule/box named "*handle*" in its subtree."""
    m = world.model
    root = m.body(body).id
    best, best_len = None, 0.0
    for g in range(m.ngeom):
        b = m.geom_bodyid[g]
        while b not in (0, root):
            b = m.body_parentid[b]
        name = m.geom(g).name
        if b != root or "handle" not in name:
            continue
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE:
            length = float(m.geom_size[g][1] + m.geom_size[g][0])
        elif m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX:
            length = float(np.max(m.geom_size[g]))
        else:
            continue
        if length > best_len:
            best, best_len = name, length
    if best is None:
        raise ValueError(f"no capsule or box geom named '*handle*' on {body!r}")
    return best


def _timed(Q, dt) -> np.ndarray:
    return np.arange(len(Q)) * dt


def articulate(prims, joint: str, target: float, verb: str) -> Motion:
    """Move `joint` to `target` (fraction of its range) with the handle grasp; raises PlanningFailed."""
    world, planner, rng = prims.world, prims.planner, prims.rng
    info = joint_info(world, joint)
    handle = find_handle(world, info.body)
    q0 = prims.start_q()
    delta = (target - info.fraction(world.data)) * (info.hi - info.lo)  # m (slide) or rad (hinge)
    grasps = prims.grasps.handle_grasps(handle, q0, rng)
    if not grasps:
        raise PlanningFailed(f"no valid grasp on the handle {handle!r}")
    dt = world.timestep
    errors = []
    for g in grasps:
        try:
            transit = planner.joint_move(q0, g.q_pre, rng, gripper=g.opening, clearance=0.005)
            approach = planner.line(g.q_pre, g.T, gripper=g.opening)
            qg = approach[-1]
            hold = g.held.gripper_qpos
            if info.kind == "slide":
                T_end = g.T.copy()
                T_end[:3, 3] += delta * info.axis
                move = planner.line(qg, T_end, gripper=hold, allow=(info.body,))
            else:
                T0 = g.T.copy()

                def pose(u, T0=T0):
                    R = rotvec_to_matrix(info.axis * delta * u)
                    T = T0.copy()
                    T[:3, :3] = R @ T0[:3, :3]
                    T[:3, 3] = info.anchor + R @ (T0[:3, 3] - info.anchor)
                    return T

                radius = float(np.linalg.norm(np.cross(info.axis, g.T[:3, 3] - info.anchor)))
                move = planner.cartesian(qg, pose, abs(delta) * max(radius, 0.02), gripper=hold, allow=(info.body,))
            qm = move[-1]
            T_up = prims.kin.fk(qm)
            T_up[2, 3] += RETREAT
            retreat = planner.line(qm, T_up, gripper=g.opening, allow=(info.body,))
        except PlanningFailed as err:
            errors.append(str(err))
            continue
        return Motion([
            Segment(_timed(transit, dt), transit, g.opening, "move to handle"),
            Segment(_timed(approach, dt), approach, g.opening, "approach handle"),
            Segment.hold(qg, GRASP_SECONDS, 1.0, "grasp handle"),
            Segment(_timed(move, dt), move, 1.0, verb),
            Segment.hold(qm, RELEASE_SECONDS, g.opening, "release handle"),
            Segment(_timed(retreat, dt), retreat, g.opening, "retreat"),
        ])
    raise PlanningFailed(f"{verb}: every handle grasp failed to plan: {errors}")
