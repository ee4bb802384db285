"""Sampling-based primitives: antipodal grasps that hold, placements, and whole tasks solved through them.

The end-to-end success rates measured over many seeds live in the report; here a few seeds per task must
pass a conservative bound, so the tests catch regressions without being flaky.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from datagen.grasp import FRICTION_CONE, MAX_WIDTH, ray_geoms
from datagen.place import OVER_RIM_SPREAD, target_region
from datagen.primitives import PrimitiveFailed, Primitives
from datagen.trajectory import execute
from sim.build import build_episode
from sim.state import StateView

SETTLE_STEPS = 250  # 0.5 s for a released object to come to rest before judging


def _solve(task: str, seed: int):
    """Build the episode and run the task's primitive sequence; returns (episode, success)."""
    ep = build_episode(task, seed, "light", "fast")
    world, p = ep.world, ep.instance.params
    prims = Primitives(world, np.random.default_rng(seed))
    steps = {
        "pick_place": [("pick", p.get("target")), ("place", p.get("target"), p.get("bin"))],
        "stack": [("pick", p.get("top")), ("place", p.get("top"), p.get("bottom"))],
        "drawer_open": [("open", "cabinet/slide")],
        "drawer_close": [("close", "cabinet/slide")],
        "drawer_put": [("open", "cabinet/slide"), ("pick", p.get("target")),
                       ("place", p.get("target"), "cabinet"), ("close", "cabinet/slide")],
    }[task]
    try:
        for name, *args in steps:
            execute(world, getattr(prims, name)(*args))
    except PrimitiveFailed:
        return ep, False
    world.step(SETTLE_STEPS)
    return ep, ep.success()


@pytest.mark.parametrize("task,seeds,need", [
    ("pick_place", (0, 1, 2, 3, 4), 4),
    ("stack", (0, 1, 2, 3), 3),
    ("drawer_open", (0, 1, 2), 2),
    ("drawer_close", (0, 1, 2), 2),
    ("drawer_put", (0, 1, 2), 2),
])
def test_tasks_are_solved_through_the_primitives(task, seeds, need):
    results = [_solve(task, s)[1] for s in seeds]
    assert sum(results) >= need, f"{task}: {results}"


@pytest.fixture(scope="module")
def episode():
    return build_episode("pick_place", 3, "light", "fast")


def test_grasps_are_antipodal_and_hold_in_simulation(episode):
    world = episode.world
    prims = Primitives(world, np.random.default_rng(0))
    obj = episode.instance.params["target"]
    grasps = prims.grasps.object_grasps(obj, prims.start_q(), np.random.default_rng(1), k=3)
    assert grasps
    m, d = world.model, world.data
    geoms = [m.geom(f"{obj}/geom").id]
    for g in grasps:
        assert g.width < MAX_WIDTH and g.held is not None and g.held.body == obj
        x, c = g.T[:3, 0], g.T[:3, 3]
        # Surface points and normals where the closing axis through the grasp meets the object.
        centre = c - g.T[:3, 2] * np.dot(c - d.xpos[m.body(obj).id], g.T[:3, 2])
        hits = []
        for sign in (1.0, -1.0):
            start = centre + sign * x * 0.2
            dist, normal = ray_geoms(m, d, geoms, start, -sign * x)
            assert dist > 0
            hits.append(normal)
        for sign, normal in zip((1.0, -1.0), hits):
            assert np.dot(normal, sign * x) >= np.cos(FRICTION_CONE) - 0.02
        np.testing.assert_allclose(g.q, prims.kin.ik(g.T, g.q_pre), atol=1e-6)


def test_picked_object_is_held_and_lifted(episode):
    world = episode.world
    obj = episode.instance.params["target"]
    z0 = world.data.xpos[world.model.body(obj).id][2]
    prims = Primitives(world, np.random.default_rng(2))
    motion = prims.pick(obj)
    assert motion.labels == ["move to pre-grasp", "approach", "grasp", "lift"]
    execute(world, motion)
    state = StateView(world)
    assert state.holding(obj)
    assert world.data.xpos[world.model.body(obj).id][2] > z0 + 0.07
    with pytest.raises(PrimitiveFailed, match="already holds"):
        prims.pick(obj)
    # A placement sample lets go over the target bin's rim, near the middle of its cavity.
    held = prims.held()
    target = episode.instance.params["bin"]
    poses = prims.places.sample(held, target, prims.start_q(), np.random.default_rng(3), k=2)
    assert poses
    region = target_region(world.model, world.data, target)
    for p in poses:
        obj_pos = (p.T @ held.T_tcp_obj)[:3, 3]
        uv = region.axes @ (obj_pos - region.centre)
        assert np.all(np.abs(uv) <= OVER_RIM_SPREAD * region.half + 1e-9) and obj_pos[2] > region.rim
    # Recover: let go, back off, return home.
    rec = prims.recover()
    assert rec.labels[0] == "release" and rec.labels[-1] == "go home"
    execute(world, rec)
    assert not state.holding(obj)
    np.testing.assert_allclose(world.arm_q(), world.variant.home, atol=0.02)


def test_a_retry_samples_anew_and_a_seed_replays():
    def first_motion(seed, calls):
        ep = build_episode("pick_place", 4, "light", "fast")
        prims = Primitives(ep.world, np.random.default_rng(seed))
        return [prims.pick(ep.instance.params["target"]) for _ in range(calls)]

    a1, a2 = first_motion(0, 2)
    (b1,) = first_motion(0, 1)
    np.testing.assert_array_equal(a1.segments[0].q, b1.segments[0].q)
    assert not np.array_equal(a1.segments[1].q[-1], a2.segments[1].q[-1])


def test_unknown_joint_and_placing_nothing_fail_clearly(episode):
    prims = Primitives(build_episode("pick_place", 5, "light", "fast").world, np.random.default_rng(0))
    with pytest.raises(PrimitiveFailed, match="no joint"):
        prims.open("nope/slide")
    with pytest.raises(PrimitiveFailed, match="holds nothing"):
        prims.place("obj0", "bin_left")
    assert mujoco.mj_name2id(prims.world.model, mujoco.mjtObj.mjOBJ_BODY, "obj0") > 0


def test_the_last_centimetres_to_a_handle_are_slow():
    """A policy a centimetre off at the planned line's full speed would hit the cabinet's front with hundreds of
    newtons (datagen/articulated.py, HANDLE_APPROACH_SPEED): the demonstrations approach a handle slowly."""
    from datagen.articulated import HANDLE_APPROACH_SPEED

    ep = build_episode("drawer_open", 0, "light", "fast")
    prims = Primitives(ep.world, np.random.default_rng(0))
    motion = prims.open("cabinet/slide")
    speeds = {}
    for seg in motion.segments:
        p = np.array([prims.kin.fk(q)[:3, 3] for q in seg.q])
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) / np.diff(seg.times) if len(p) > 1 else [0.0]
        speeds[seg.label] = max(speeds.get(seg.label, 0.0), float(np.max(v)))
    assert 0.5 * HANDLE_APPROACH_SPEED < speeds["approach handle"] <= HANDLE_APPROACH_SPEED * 1.01
    assert speeds["move to handle"] > 3 * HANDLE_APPROACH_SPEED  # only the approach is slow


def test_a_drawer_handle_taken_from_the_front_is_level_and_opens_the_drawer():
    """handle_grasp "front": the approach is level and points away from the robot, the fingers close above and
    below the bar (the closing axis vertical), the part still moves to its target, and the fingers, wide open,
    leave straight back out along the approach (up would take the lower finger into the bar)."""
    from datagen.articulated import RETREAT

    ep = build_episode("drawer_open", 310000, "light", "fast")
    prims = Primitives(ep.world, np.random.default_rng(0), handle_grasp="front")
    motion = prims.open("cabinet/slide")
    labels = [s.label for s in motion.segments]
    T = prims.kin.fk(motion.segments[labels.index("grasp handle")].q[0])
    assert abs(T[2, 2]) < 0.2 and abs(T[2, 0]) > 0.95  # approach level, closing axis vertical
    assert np.dot(T[:2, 2], T[:2, 3]) > 0  # away from the base
    retreat = motion.segments[-1]
    assert motion.segments[labels.index("release handle")].gripper == retreat.gripper == 0.0  # wide open
    p0, p1 = (prims.kin.fk(retreat.q[i])[:3, 3] for i in (0, -1))
    T_end = prims.kin.fk(retreat.q[0])
    np.testing.assert_allclose(p1 - p0, -RETREAT * T_end[:3, 2], atol=0.005)
    with pytest.raises(ValueError, match="handle_grasp 'side'"):
        Primitives(ep.world, np.random.default_rng(0), handle_grasp="side")


def test_a_datagen_episode_records_a_front_handle_grasp_and_completes_the_drawers():
    from datagen.episode import DatagenConfig, run_episode

    for task in ("drawer_open", "drawer_close"):
        ep = run_episode(task, 310001, DatagenConfig(dr="heavy", handle_grasp="front"))
        assert ep.meta["success"] and ep.meta["handle_grasp"] == "front", ep.meta["attempts"]
    assert "handle_grasp" not in run_episode("drawer_open", 310001, DatagenConfig(dr="heavy")).meta
