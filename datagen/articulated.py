"""Opening and closing articulated parts: grasp the handle, move it along the joint, release, retreat.

Works from the model alone: the joint's type, range, axis and anchor come from MuJoCo, the handle is the
most elongated capsule/box geom named "*handle*" in the moving body's subtree. A slide joint is driven by a
straight TCP line along its axis. A hinge is opened by a rigid grasp arc for the first `RIGID_ARC` rad, then
a loosened grasp carries the handle on to the stop while the wrist turns back (`_open_hinge`), and shut by a
fingertip push along the arc (`_push_hinge`). While the part moves with the hand, contacts with the moving part are allowed; everything
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
# The last few centimetres to a handle at a careful 5 cm/s, as a person teaching it would: a finger that meets
# the stiff front 1 cm early (the distilled policy's chunks scatter that much) presses ~1.9 kN per m/s at the
# touch (sim, tests/test_controller_contact.py's cabinet), so at the full 0.225 m/s of a planned line it trips
# the arm's 150 N force limit at once; at 5 cm/s it touches with ~90 N.
HANDLE_APPROACH_SPEED = 0.05  # m/s


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
    """Move `joint` to `target` (fraction of its range); raises PlanningFailed.

    A slide joint and closing a hinge from nearly closed: the handle grasp moved along the joint. Opening a
    hinge: `_open_hinge`; closing an open hinge: `_push_hinge` (fingertip push), the rigid grasp arc as a
    fallback.
    """
    info = joint_info(prims.world, joint)
    if info.kind == "hinge":
        frac = info.fraction(prims.world.data)
        if target > max(frac + 0.02, 0.5):
            return _open_hinge(prims, info, target, verb)
        if target < frac - 0.02:
            try:
                return _push_hinge(prims, info, target, verb)
            except PlanningFailed as err:
                push_err = str(err)
            try:
                return _grasp_move(prims, info, target, verb)
            except PlanningFailed as err:
                raise PlanningFailed(f"{err}; fingertip push: {push_err}") from None
    return _grasp_move(prims, info, target, verb)


def _handle_motion(prims, info: JointInfo, verb: str, after_grasp) -> Motion:
    """Try each sampled handle grasp: transit to it, approach, close; then `after_grasp(g, qg)` plans the
    part-specific rest (a list of Segments) or raises PlanningFailed, and the next grasp is tried."""
    world, planner, rng = prims.world, prims.planner, prims.rng
    handle = find_handle(world, info.body)
    q0 = prims.start_q()
    front = info.kind == "slide" and prims.handle_grasp == "front"
    grasps = prims.grasps.handle_grasps(handle, q0, rng, front=front)
    if not grasps:
        raise PlanningFailed(f"no valid grasp on the handle {handle!r}")
    dt = world.timestep
    errors = []
    for g in grasps:
        try:
            transit = planner.joint_move(q0, g.q_pre, rng, gripper=g.opening, clearance=0.005)
            approach = planner.line(g.q_pre, g.T, gripper=g.opening, tcp_speed=HANDLE_APPROACH_SPEED)
            qg = approach[-1]
            rest = after_grasp(g, qg)
        except PlanningFailed as err:
            errors.append(str(err))
            continue
        return Motion([
            Segment(_timed(transit, dt), transit, g.opening, "move to handle"),
            Segment(_timed(approach, dt), approach, g.opening, "approach handle"),
            Segment.hold(qg, GRASP_SECONDS, 1.0, "grasp handle"),
            *rest,
        ])
    raise PlanningFailed(f"{verb}: every handle grasp failed to plan: {errors}")


def _grasp_move(prims, info: JointInfo, target: float, verb: str) -> Motion:
    """Grasp the handle, move it along the joint with a rigid grasp, release, retreat up."""
    world, planner = prims.world, prims.planner
    delta = (target - info.fraction(world.data)) * (info.hi - info.lo)  # m (slide) or rad (hinge)
    dt = world.timestep

    def after_grasp(g, qg):
        hold = g.held.gripper_qpos
        if info.kind == "slide":
            T_end = g.T.copy()
            T_end[:3, 3] += delta * info.axis
            move = planner.line(qg, T_end, gripper=hold, allow=(info.body,))
        else:
            T0 = g.T.copy()

            def pose(u):
                R = rotvec_to_matrix(info.axis * delta * u)
                T = T0.copy()
                T[:3, :3] = R @ T0[:3, :3]
                T[:3, 3] = info.anchor + R @ (T0[:3, 3] - info.anchor)
                return T

            radius = float(np.linalg.norm(np.cross(info.axis, g.T[:3, 3] - info.anchor)))
            move = planner.cartesian(qg, pose, abs(delta) * max(radius, 0.02), gripper=hold, allow=(info.body,))
        qm = move[-1]
        # A front grasp's fingers leave along the bar's sides, above and below it: wide open, so that an arm a
        # centimetre off its path (a policy's, or DART noise's) does not drag the drawer back out by a fingertip.
        let_go = g.opening if _from_above(g.T) else 0.0
        retreat = planner.line(qm, _retreat_pose(prims.kin.fk(qm)), gripper=let_go, allow=(info.body,))
        return [
            Segment(_timed(move, dt), move, 1.0, verb),
            Segment.hold(qm, RELEASE_SECONDS, let_go, "release handle"),
            Segment(_timed(retreat, dt), retreat, let_go, "retreat"),
        ]

    return _handle_motion(prims, info, verb, after_grasp)


def _from_above(T: np.ndarray) -> bool:
    """A handle grasp from above (the approach pointing down), not from the front (level)."""
    return bool(T[2, 2] < -0.7)


def _retreat_pose(T: np.ndarray) -> np.ndarray:
    """Where the open fingers leave a handle to: straight up from a grasp from above, straight back out along
    the approach from a grasp from the front (up would take the lower finger into the bar)."""
    T = T.copy()
    if _from_above(T):
        T[2, 3] += RETREAT
    else:
        T[:3, 3] -= RETREAT * T[:3, 2]
    return T


# -- hinges ------------------------------------------------------------------------------------------------------
RIGID_ARC = 0.9  # rad: how far a rigid handle grasp turns the wrist with a lid (reachable, clear of singularities)
LOOSEN = 0.03  # gripper command below the one that just closes on the handle: the bar turns between the pads
OVERDRIVE = 0.06  # rad past the joint's upper limit: the handle is pressed against the stop
LOOSEN_SECONDS = 0.3
PUSH_RADIUS = 0.09  # m from the hinge axis where the fingertips push a lid shut
PUSH_OFFSET = 0.026  # m from the lid's hinge plane to the TCP: plate (6 mm) + finger half-thickness
PUSH_ABOVE = 0.10  # m: the push starts with a straight descent from this high above its first pose


def _command_for(world, gripper_qpos) -> float:
    """The gripper command whose unobstructed closure puts the driver joints where `gripper_qpos` has them
    (e.g. closed on a handle); the compliant follower joints are left out."""
    from datagen.collision import _OPENINGS, gripper_table

    m = world.model
    adr = np.array([m.jnt_qposadr[j] for j in range(m.njnt) if m.joint(j).name.startswith("gripper/")])
    drivers = np.isin(adr, np.atleast_1d(world.gripper_qpos_adr))
    table = gripper_table(world, adr)[:, drivers]
    c = np.linspace(0.0, 1.0, 201)
    angles = np.column_stack([np.interp(c, np.asarray(_OPENINGS, float), col) for col in table.T])
    want = np.asarray(gripper_qpos, float)[drivers]
    return float(c[np.argmin(np.linalg.norm(angles - want[None], axis=1))])


def _hinge_pose(info: JointInfo, T0: np.ndarray, angle: float, turn: float) -> np.ndarray:
    """T0 carried `angle` rad about the hinge, its orientation turned by only `turn` rad."""
    T = T0.copy()
    T[:3, :3] = rotvec_to_matrix(info.axis * turn) @ T0[:3, :3]
    T[:3, 3] = info.anchor + rotvec_to_matrix(info.axis * angle) @ (T0[:3, 3] - info.anchor)
    return T


def _open_hinge(prims, info: JointInfo, target: float, verb: str) -> Motion:
    """Open a lid as a person does: lift it by the handle with a firm grasp while the wrist stays comfortable
    (`RIGID_ARC`), then loosen the fingers so the bar turns between the pads, and carry the handle on along
    its circle to the joint's upper stop while the wrist turns back to pointing down (the bar rolls between
    the pads; it is caged, never pulled towards the fingertips). Release and lift straight off the bar.

    With a rigid grasp the wrist would have to turn the full ~90 deg with the lid, ending behind the box
    pointing back at the robot: past ~70 deg that leaves the reachable set or crosses a wrist singularity.
    """
    world, planner = prims.world, prims.planner
    now = float(world.data.qpos[info.qpos_adr])
    # The lid is driven to its stop (it falls back from anywhere short of upright), the target only decides
    # whether to go there at all.
    goal = max(info.lo + target * (info.hi - info.lo), info.hi + OVERDRIVE)
    rigid = float(np.clip(goal - now, 0.0, RIGID_ARC))
    dt = world.timestep

    def after_grasp(g, qg):
        hold = g.held.gripper_qpos
        T0 = g.T.copy()
        radius = float(np.linalg.norm(np.cross(info.axis, T0[:3, 3] - info.anchor)))
        lift = planner.cartesian(qg, lambda u: _hinge_pose(info, T0, rigid * u, rigid * u),
                                 rigid * max(radius, 0.02), gripper=hold, allow=(info.body,))
        ql = lift[-1]
        rest = goal - now - rigid
        carry = planner.cartesian(ql, lambda u: _hinge_pose(info, T0, rigid + rest * u, rigid * (1.0 - u)),
                                  rest * max(radius, 0.02) + 0.05 * rigid, gripper=hold, allow=(info.body,))
        qc = carry[-1]
        T_back = prims.kin.fk(qc)
        T_back[2, 3] += RETREAT
        retreat = planner.line(qc, T_back, gripper=g.opening, allow=(info.body,))
        loose = max(_command_for(world, hold) - LOOSEN, g.opening)
        return [
            Segment(_timed(lift, dt), lift, 1.0, verb),
            Segment.hold(ql, LOOSEN_SECONDS, loose, "loosen grasp"),
            Segment(_timed(carry, dt), carry, loose, verb),
            Segment.hold(qc, RELEASE_SECONDS, g.opening, "release handle"),
            Segment(_timed(retreat, dt), retreat, g.opening, "retreat"),
        ]

    return _handle_motion(prims, info, verb, after_grasp)


def _push_frame(info: JointInfo, world) -> tuple[np.ndarray, float]:
    """(unit vector from the hinge axis towards the handle, perpendicular to the axis; the angle now)."""
    m, d = world.model, world.data
    g = m.geom(find_handle(world, info.body)).id
    v = d.geom_xpos[g] - info.anchor
    v -= np.dot(v, info.axis) * info.axis
    return v / np.linalg.norm(v), float(d.qpos[info.qpos_adr])


def _push_hinge(prims, info: JointInfo, target: float, verb: str) -> Motion:
    """Shut a lid with the closed fingertips: come down behind it, sweep its outer face down along the arc
    to the target angle (the fingers pointing down throughout), and lift away."""
    from datagen.grasp import _best_flip

    world, planner, rng = prims.world, prims.planner, prims.rng
    q0 = prims.start_q()
    v_now, now = _push_frame(info, world)
    goal = info.lo + target * (info.hi - info.lo)
    start = min(now + 0.12, info.hi + 0.12)
    x = info.axis.copy()
    z = np.array([0.0, 0.0, -1.0])
    z -= np.dot(z, x) * x
    z /= np.linalg.norm(z)
    R = _best_flip(np.column_stack([x, np.cross(z, x), z]), prims.kin.fk(q0)[:3, :3])

    def pose(angle: float) -> np.ndarray:
        Rl = rotvec_to_matrix(info.axis * (angle - now))
        v = Rl @ v_now
        n = np.cross(info.axis, v)  # the lid's outer face normal (the way it opens)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = info.anchor + PUSH_RADIUS * v + PUSH_OFFSET * n
        return T

    dt = world.timestep
    errors = []
    for above in (PUSH_ABOVE, 0.06):
        try:
            T_start = pose(start)
            T_pre = T_start.copy()
            T_pre[2, 3] += above
            q_pre = prims.kin.ik(T_pre, q0)
            transit = planner.joint_move(q0, q_pre, rng, gripper=1.0, clearance=0.005)
            descend = planner.line(q_pre, T_start, gripper=1.0)
            qs = descend[-1]
            sweep = planner.cartesian(qs, lambda u: pose(start + (goal - start) * u),
                                      abs(goal - start) * PUSH_RADIUS + 0.01, gripper=1.0, allow=(info.body,))
            qe = sweep[-1]
            T_up = prims.kin.fk(qe)
            T_up[2, 3] += RETREAT
            retreat = planner.line(qe, T_up, gripper=1.0, allow=(info.body,))
        except (PlanningFailed, ValueError) as err:
            errors.append(str(err))
            continue
        return Motion([
            Segment(_timed(transit, dt), transit, 1.0, "move behind lid"),
            Segment(_timed(descend, dt), descend, 1.0, "approach lid"),
            Segment(_timed(sweep, dt), sweep, 1.0, verb),
            Segment(_timed(retreat, dt), retreat, 1.0, "retreat"),
        ])
    raise PlanningFailed(f"{verb}: fingertip push failed to plan: {errors}")
