"""The planner API of data generation: pick, place, open, close, recover, each returning a Motion.

Every call plans from the live sim state (object poses, the arm's commanded configuration, what the gripper
holds) and draws its samples from the caller's rng, so a retry after a failure gets a new grasp, placement
and path, and an episode replays identically from the same seed. Nothing moves until the caller runs the
Motion with `datagen.trajectory.execute`; failures raise PrimitiveFailed with the reason, for the data
generator's retry and labelling logic.

    pick(object):         plan to pre-grasp -> straight approach -> close -> straight lift
    place(object, target): plan to pre-place -> straight descent -> open -> straight retreat
    open(joint)/close(joint): see datagen.articulated
    recover():            open the gripper -> retreat up -> plan home
"""

from __future__ import annotations

import numpy as np

from datagen import articulated
from datagen.collision import CollisionChecker, Held, safety_workspace
from datagen.grasp import GraspSampler
from datagen.motion import MotionPlanner, PlanningFailed, motion_limits
from datagen.place import PlaceSampler
from datagen.trajectory import Motion, Segment
from sim.kinematics import Kinematics
from sim.robot import GRIPPER_PREFIX, TCP_OFFSET_Z, get_variant
from sim.state import StateView

LIFT = 0.10  # m, straight up after grasping
RETREAT = 0.10  # m, straight up after releasing
GRASP_SECONDS, RELEASE_SECONDS = 0.6, 0.5


class PrimitiveFailed(RuntimeError):
    """A primitive found no valid sample or no plan; `reason` says which and why."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def _timed(Q, dt) -> np.ndarray:
    return np.arange(len(Q)) * dt

# How a drawer's (slide joint's) handle is taken: from above, or from the front, level (datagen/grasp.py); lids
# (hinges) are always taken from above.
HANDLE_GRASPS = ("top", "front")


class Primitives:
    def __init__(self, world, rng: np.random.Generator, variant: str = "ur5e", budget: float = 2.0,
                 handle_grasp: str = "top"):
        if handle_grasp not in HANDLE_GRASPS:
            raise ValueError(f"handle_grasp {handle_grasp!r}: expected one of {HANDLE_GRASPS}")
        self.world, self.rng, self.budget, self.handle_grasp = world, rng, budget, handle_grasp
        v = get_variant(variant)
        self.kin = Kinematics.with_tcp_z(v, TCP_OFFSET_Z)
        self.checker = CollisionChecker(world, margin=0.01, workspace=safety_workspace(v.name))
        self.planner = MotionPlanner(self.checker, self.kin, motion_limits(v), world.timestep)
        self.grasps = GraspSampler(world, self.checker, self.kin)
        self.places = PlaceSampler(world, self.checker, self.kin)
        self.dt = world.timestep

    # -- live state ----------------------------------------------------------------------------------------
    def start_q(self) -> np.ndarray:
        """Where a new motion starts: the commanded configuration (continuity), synced checker."""
        self.checker.sync()
        q_cmd, q = self.world.arm_target(), self.world.arm_q()
        return q_cmd if np.max(np.abs(q_cmd - q)) < 0.05 else q

    def free_objects(self) -> list[str]:
        m = self.world.model
        return [m.body(b).name for b in range(1, m.nbody)
                if m.body_jntnum[b] == 1 and m.jnt_type[m.body_jntadr[b]] == 0]

    def held(self) -> Held | None:
        """The object both pads touch, with its live pose in the TCP frame and the gripper's angles."""
        state = StateView(self.world)
        for name in self.free_objects():
            if state.holding(name):
                d, m = self.world.data, self.world.model
                bid = m.body(name).id
                T_obj = np.eye(4)
                T_obj[:3, :3] = d.xmat[bid].reshape(3, 3)
                T_obj[:3, 3] = d.xpos[bid]
                grip = d.qpos[self.checker.gripper_adr].copy()
                return Held(name, np.linalg.inv(self.world.tcp_pose()) @ T_obj, grip)
        return None

    def _supports(self, obj: str) -> tuple:
        """(obj, other) pairs in contact now: the lift may start touching what the object stood on."""
        m, d = self.world.model, self.world.data
        bid = m.body(obj).id
        pairs = set()
        for i in range(d.ncon):
            g1, g2 = d.contact.geom1[i], d.contact.geom2[i]
            for a, b in ((g1, g2), (g2, g1)):
                if m.geom_bodyid[a] == bid and not m.body(m.geom_bodyid[b]).name.startswith(GRIPPER_PREFIX):
                    pairs.add((obj, m.geom(b).name or m.body(m.geom_bodyid[b]).name))
        return tuple(sorted(pairs))

    # -- primitives ---------------------------------------------------------------------------------------------
    def pick(self, obj: str) -> Motion:
        q0 = self.start_q()
        held = self.held()
        if held is not None:
            raise PrimitiveFailed(f"pick({obj}): the gripper already holds {held.body}")
        grasps = self.grasps.object_grasps(obj, q0, self.rng)
        if not grasps:
            raise PrimitiveFailed(f"pick({obj}): no reachable, collision-free grasp that holds in simulation")
        allow = self._supports(obj)
        errors = []
        T0 = self.kin.fk(q0)
        # a grasp whose approach the gripper is already on (after reopen()) goes on down from here
        ranked = sorted(((_on_approach(T0, g), g) for g in grasps), key=lambda p: not p[0])
        for on_line, g in ranked:
            try:
                transit = None
                if on_line:
                    approach = self.planner.line(q0, g.T, gripper=g.opening)
                else:
                    transit = self.planner.joint_move(q0, g.q_pre, self.rng, self.budget, gripper=g.opening,
                                                      clearance=0.005)
                    approach = self.planner.line(g.q_pre, g.T, gripper=g.opening)
                qg = approach[-1]
                T_lift = self.kin.fk(qg)
                T_lift[2, 3] += LIFT
                lift = self.planner.line(qg, T_lift, held=g.held, allow=allow)
            except PlanningFailed as err:
                errors.append(str(err))
                continue
            segments = [] if transit is None else [
                Segment(_timed(transit, self.dt), transit, g.opening, "move to pre-grasp")]
            return Motion([*segments, Segment(_timed(approach, self.dt), approach, g.opening, "approach"),
                           Segment.hold(qg, GRASP_SECONDS, 1.0, "grasp"),
                           Segment(_timed(lift, self.dt), lift, 1.0, "lift")])
        raise PrimitiveFailed(f"pick({obj}): {len(grasps)} grasps, none planned: {errors}")

    def place(self, obj: str, target: str) -> Motion:
        q0 = self.start_q()
        held = self.held()
        if held is None or held.body != obj:
            raise PrimitiveFailed(f"place({obj}, {target}): the gripper holds {held.body if held else 'nothing'}")
        poses = self.places.sample(held, target, q0, self.rng)
        if not poses:
            raise PrimitiveFailed(f"place({obj}, {target}): no reachable, collision-free placement")
        errors = []
        for p in poses:
            try:
                transit = self.planner.joint_move(q0, p.q_pre, self.rng, self.budget, held=held, clearance=0.005)
                descend = self.planner.line(p.q_pre, p.T, held=held)
                qp = descend[-1]
                T_up = self.kin.fk(qp)
                T_up[2, 3] += RETREAT
                retreat = self.planner.line(qp, T_up, gripper=p.release, allow=(obj,))
            except PlanningFailed as err:
                errors.append(str(err))
                continue
            return Motion([Segment(_timed(transit, self.dt), transit, 1.0, "move to pre-place"),
                           Segment(_timed(descend, self.dt), descend, 1.0, "descend"),
                           Segment.hold(qp, RELEASE_SECONDS, p.release, "release"),
                           Segment(_timed(retreat, self.dt), retreat, p.release, "retreat")])
        raise PrimitiveFailed(f"place({obj}, {target}): {len(poses)} placements, none planned: {errors}")

    def open(self, joint: str) -> Motion:
        return self._articulate(joint, articulated.OPEN_TARGET, "open")

    def close(self, joint: str) -> Motion:
        return self._articulate(joint, articulated.CLOSED_TARGET, "close")

    def _articulate(self, joint: str, target: float, verb: str) -> Motion:
        if self.held() is not None:
            raise PrimitiveFailed(f"{verb}({joint}): the gripper holds {self.held().body}")
        try:
            return articulated.articulate(self, joint, target, f"{verb} {joint}")
        except (PlanningFailed, KeyError, ValueError) as err:
            raise PrimitiveFailed(f"{verb}({joint}): {err}") from None

    def reopen(self) -> Motion:
        """Open the gripper where it is: after a close on air above an object that did not move, so that the
        next pick goes on down from here. Backing off home instead would show, from the same open-gripper
        view above the object, a retreat where every other demonstration descends (a policy averages the two
        and hovers)."""
        return Motion([Segment.hold(self.start_q(), RELEASE_SECONDS, 0.0, "release")])

    def recover(self) -> Motion:
        """Let go, back off upwards (tolerating what the arm touches now), and plan to the home pose."""
        self.checker.sync()
        q0 = self.world.arm_q()
        touching = tuple(sorted({n for a, b, _ in self.checker.collisions(q0, gripper=0.0) for n in (a, b)}))
        touching = tuple(n for n in touching if n in _names(self.world.model))
        segs = [Segment.hold(q0, RELEASE_SECONDS, 0.0, "release")]
        q = q0
        T_up = self.kin.fk(q0)
        T_up[2, 3] += RETREAT
        try:
            up = self.planner.line(q0, T_up, gripper=0.0, allow=touching)
            segs.append(Segment(_timed(up, self.dt), up, 0.0, "retreat"))
            q = up[-1]
        except PlanningFailed:
            pass  # e.g. already at the top of the workspace: plan home from here
        try:
            home = self.planner.joint_move(q, np.asarray(self.world.variant.home), self.rng, self.budget,
                                           gripper=0.0, allow=touching if q is q0 else ())
        except PlanningFailed as err:
            raise PrimitiveFailed(f"recover(): {err}") from None
        segs.append(Segment(_timed(home, self.dt), home, 0.0, "go home"))
        return Motion(segs)


def _on_approach(T: np.ndarray, g, lateral: float = 0.01, degrees: float = 5.0) -> bool:
    """Whether TCP pose T lies on grasp g's straight approach (between its pre-grasp and grasp poses, within
    `lateral` of the line, turned at most `degrees` from the grasp's orientation)."""
    a, b = g.T_pre[:3, 3], g.T[:3, 3]
    axis = b - a
    s = float(np.dot(T[:3, 3] - a, axis) / max(float(np.dot(axis, axis)), 1e-12))
    off = np.linalg.norm(T[:3, 3] - (a + s * axis))
    cos = (np.trace(g.T[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
    return 0.0 <= s < 1.0 and off < lateral and cos > np.cos(np.radians(degrees))


def _names(m) -> set:
    return {m.geom(g).name for g in range(m.ngeom) if m.geom(g).name} | {m.body(b).name for b in range(m.nbody)}
