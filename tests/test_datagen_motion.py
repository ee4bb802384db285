"""The planning layer: collision checker vs MuJoCo's own contacts, RRT around an obstacle, limits, determinism."""

from __future__ import annotations

import copy
import time

import mujoco
import numpy as np
import pytest

from datagen.collision import CollisionChecker, Held
from datagen.motion import MotionPlanner, PlanningFailed, limit_ratio, motion_limits, trapezoid
from datagen.trajectory import Motion, Segment, execute
from sim.build import build_episode
from sim.fidelity import apply_fidelity
from sim.kinematics import Kinematics
from sim.robot import TCP_OFFSET_Z
from sim.scene import base_scene
from sim.tasks.scripted import top_down
from sim.world import World

WALL_X = 0.0

try:
    from safety.harness import check_stream
    from safety.limits import default_limits
except ImportError:  # the safety layer is optional here; datagen's own limits are checked regardless
    check_stream = default_limits = None


@pytest.fixture(scope="module")
def walled():
    """The bare scene with a tall wall across the table between two work spots."""
    spec = base_scene("ur5e")
    apply_fidelity(spec, "fast")
    spec.worldbody.add_geom(name="wall", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.15, 0.25],
                            pos=[WALL_X, 0.62, 0.25])
    world = World(spec.compile(), "ur5e")
    kin = Kinematics.with_tcp_z(world.variant, TCP_OFFSET_Z)
    checker = CollisionChecker(world, margin=0.01)
    planner = MotionPlanner(checker, kin, motion_limits(world.variant), world.timestep)
    q0 = world.arm_q()
    qa = kin.ik(top_down([-0.22, 0.55, 0.12], 0.0), q0)
    qb = kin.ik(top_down([0.22, 0.55, 0.12], 0.0), qa)
    return world, kin, checker, planner, qa, qb


@pytest.fixture(scope="module")
def scene():
    ep = build_episode("drawer_put", 0, "light", "fast")
    return ep.world, CollisionChecker(ep.world, margin=0.01)


def _live_collision(world, checker, q, tol):
    """Robot contacts by a full mj_forward on a copy of the live data, deeper than -tol."""
    d = copy.copy(world.data)
    d.qpos[world.arm_qpos_adr] = q
    mujoco.mj_forward(world.model, d)
    for i in range(d.ncon):
        g1, g2, dist = d.contact.geom1[i], d.contact.geom2[i], d.contact.dist[i]
        robot = checker.robot_geoms[g1] or checker.robot_geoms[g2]
        internal = checker.gripper_geoms[g1] and checker.gripper_geoms[g2]
        if robot and not internal and dist < -tol:
            return True
    return False


def test_checker_agrees_with_mj_forward_contacts(scene):
    world, checker = scene
    rng = np.random.default_rng(0)
    n_coll = 0
    for q in rng.uniform(-np.pi, np.pi, (400, 6)):
        free = checker.is_free(q)
        n_coll += not free
        # Depths within 1 mm may differ (MuJoCo's convex solver with and without margin): no false verdicts
        # beyond that.
        if free:
            assert not _live_collision(world, checker, q, 1e-3), q
        else:
            assert _live_collision(world, checker, q, -1e-3), (q, checker.collisions(q))
    assert 50 < n_coll < 350  # both verdicts exercised


def test_checker_is_fast_and_leaves_the_live_world_alone(scene):
    world, checker = scene
    before = world.data.qpos.copy()
    Q = np.random.default_rng(1).uniform(-np.pi, np.pi, (2000, 6))
    t = time.perf_counter()
    for q in Q:
        checker.is_free(q)
    per = (time.perf_counter() - t) / len(Q)
    assert per < 300e-6, f"{per * 1e6:.0f} us per check"
    np.testing.assert_array_equal(world.data.qpos, before)


def test_held_object_moves_with_the_tcp_and_may_touch_the_pads(scene):
    world, checker = scene
    kin = Kinematics.with_tcp_z(world.variant, TCP_OFFSET_Z)
    q_home = world.arm_q()
    # A block hanging 5 cm below the TCP: free in the air, colliding once the TCP is 3 cm above the table.
    T_obj = np.eye(4)
    T_obj[2, 3] = 0.05
    held = Held("obj0", T_obj)
    assert checker.is_free(q_home, held=held)
    q_low = kin.ik(top_down([0.0, 0.35, 0.04], 0.0), q_home)
    assert checker.is_free(q_low, gripper=0.0)
    hits = checker.collisions(q_low, held=held, gripper=0.0)
    assert any("obj0/geom" in pair for hit in hits for pair in hit[:2]) and any("table" in h[:2] for h in hits)
    # Between the pads (TCP frame origin): contacts with the gripper are allowed.
    assert checker.is_free(q_home, held=Held("obj0", np.eye(4)), gripper=1.0)


def test_trapezoid_reaches_the_end_within_limits():
    s = trapezoid(1.0, 0.5, 2.0, 0.002)
    assert s[0] == 0.0 and s[-1] == 1.0 and np.all(np.diff(s) >= 0)
    v = np.diff(s) / 0.002
    a = np.diff(v) / 0.002
    assert v.max() <= 0.5 + 1e-9 and np.abs(a).max() <= 2.0 + 1e-6
    assert len(s) * 0.002 < 1.0 / 0.5 + 0.5 / 2.0 + 0.01  # time-optimal up to one step
    sj = trapezoid(1.0, 0.5, 2.0, 0.002, j=50.0)  # jerk-limited: a moving average over 2a/j
    P = np.concatenate([[0.0, 0.0], sj, [1.0, 1.0]])
    v, a = np.diff(P) / 0.002, np.diff(P, 2) / 0.002**2
    j = np.diff(P, 3) / 0.002**3
    assert v.max() <= 0.5 + 1e-9 and np.abs(a).max() <= 2.0 + 1e-6 and np.abs(j).max() <= 50.0 + 1e-3
    assert len(sj) * 0.002 < len(s) * 0.002 + 2 * 2.0 / 50.0 + 0.01


def test_planner_goes_around_an_obstacle_and_every_sample_is_free(walled):
    world, kin, checker, planner, qa, qb = walled
    line = np.linspace(qa, qb, 200)
    assert planner.first_collision(line, res=0.002) >= 0, "the straight joint move must hit the wall"
    Q = planner.joint_move(qa, qb, np.random.default_rng(0))
    np.testing.assert_allclose(Q[0], qa)
    np.testing.assert_allclose(Q[-1], qb)
    assert np.max(np.abs(np.diff(Q, axis=0))) < 0.01  # fine resolution: samples at the 2 ms step
    assert all(checker.is_free(q) for q in Q)
    mid = 0.5 * (Q[1:] + Q[:-1])
    assert all(checker.is_free(q) for q in mid[::3])


def test_time_parameterized_trajectories_respect_limits(walled):
    world, kin, checker, planner, qa, qb = walled
    lim, dt = planner.limits, world.timestep
    for Q in (planner.joint_move(qa, qb, np.random.default_rng(1)),
              planner.line(qa, top_down([-0.32, 0.42, 0.05], 0.4))):
        # Finite differences of a stream at rest before and after, as the safety monitor computes them.
        P = np.concatenate([Q[:1], Q[:1], Q, Q[-1:], Q[-1:]])
        v = np.diff(P, axis=0) / dt
        a = np.diff(v, axis=0) / dt
        j = np.diff(a, axis=0) / dt
        T = kin.fk_batch(Q)
        tcp = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt
        assert np.all(np.abs(v) <= lim.velocity * (1 + 1e-6))
        assert np.all(np.abs(a) <= lim.acceleration * (1 + 1e-6))
        assert np.all(np.abs(j) <= lim.jerk * (1 + 1e-6))
        assert tcp.max() <= lim.tcp_speed * (1 + 1e-6) <= 0.25
        assert limit_ratio(Q, dt, lim, kin) <= 1 + 1e-6
        if check_stream is not None:  # the safety layer's own verdict on the stream, with its default limits
            assert check_stream(Q, dt, default_limits("ur5e")) == []


def test_cartesian_line_is_straight(walled):
    world, kin, checker, planner, qa, qb = walled
    T1 = top_down([-0.22, 0.55, 0.02], 0.0)
    Q = planner.line(qa, T1)
    p = kin.fk_batch(Q)[:, :3, 3]
    p0 = kin.fk(qa)[:3, 3]
    d = (T1[:3, 3] - p0) / np.linalg.norm(T1[:3, 3] - p0)
    off = (p - p0) - np.outer((p - p0) @ d, d)
    assert np.linalg.norm(off, axis=1).max() < 5e-4
    np.testing.assert_allclose(p[-1], T1[:3, 3], atol=1e-4)


def test_planning_is_deterministic_per_seed(walled):
    world, kin, checker, planner, qa, qb = walled
    a = planner.plan(qa, qb, np.random.default_rng(7))
    b = planner.plan(qa, qb, np.random.default_rng(7))
    c = planner.plan(qa, qb, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_planning_failures_say_why(walled):
    world, kin, checker, planner, qa, qb = walled
    q_in_wall = kin.ik(top_down([WALL_X, 0.6, 0.2], 0.0), qa)
    with pytest.raises(PlanningFailed, match="goal configuration in collision"):
        planner.plan(qa, q_in_wall, np.random.default_rng(0))
    with pytest.raises(PlanningFailed, match="Cartesian move: collision"):
        planner.line(qa, top_down([0.1, 0.55, 0.12], 0.0))


def test_execute_tracks_segments_and_reports_labels(walled):
    world, kin, checker, planner, qa, qb = walled
    world.reset()
    Q = planner.joint_move(world.arm_q(), qa, np.random.default_rng(0))
    motion = Motion([Segment(np.arange(len(Q)) * world.timestep, Q, 0.0, "move"),
                     Segment.hold(qa, 0.3, 1.0, "close")])
    seen = []
    execute(world, motion, observer=lambda w, label: seen.append(label))
    assert seen.count("move") == len(Q) - 1 and seen.count("close") == 150
    assert np.max(np.abs(world.arm_q() - qa)) < 0.01
    assert world.gripper_command() == 1.0
