"""safety.collision: the guard on the MuJoCo model slows near and stops before contact (scenario tests)."""

from __future__ import annotations

import warnings
from pathlib import Path

import mujoco
import numpy as np
import pytest

from safety.collision import TABLE_GEOM, CollisionGuard
from safety.filter import SafetyFilter
from safety.harness import Command, check_stream, run_stream
from safety.limits import default_limits, load_limits

warnings.simplefilter("ignore", UserWarning)
HOME = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
BOX = (-0.35, 0.21, 0.56, -0.23, 0.33, 0.68)  # beside the wrist at home height, well above the TCP's path


@pytest.fixture(scope="module")
def box_guard():
    lim = load_limits(None, "ur5e", {"workspace.keepout": [list(BOX)]})
    return lim, CollisionGuard(lim)


@pytest.fixture(scope="module")
def table_guard():
    lim = default_limits("ur5e")
    return lim, CollisionGuard(lim)


def _clearance(guard, q, obstacle: str, fingers: bool = True) -> float:
    """True smallest distance from any robot collision geom to one obstacle geom (no broadphase)."""
    m, d = guard.model, guard.data
    d.qpos[guard._qadr] = q
    mujoco.mj_kinematics(m, d)
    o = m.geom(obstacle).id
    out = np.inf
    for g in range(m.ngeom):
        body = m.body(m.geom_bodyid[g]).name
        if not m.geom_contype[g] or m.geom_bodyid[g] == 0 or body == "shoulder_link":
            continue
        if not fingers and any(p in body for p in ("driver", "coupler", "spring", "follower", "pad")):
            continue
        out = min(out, mujoco.mj_geomDistance(m, d, g, o, 1.0, None))
    return out


def test_model_pairs_exclude_structural_neighbours(table_guard):
    _, guard = table_guard
    labels = {tuple(sorted(p)) for p in guard.labels}
    assert ("gripper/base_mount", "wrist_2_link") not in labels  # always touching: structural
    assert not any("shoulder_link" in p and TABLE_GEOM in p for p in labels)
    assert not any(TABLE_GEOM in p and "pad" in "".join(p) for p in labels)
    check = guard.check(HOME, HOME)
    assert check.scale == 1.0 and check.clearance_now >= guard.slow


def test_scale_ramps_between_slow_and_stop(table_guard):
    _, g = table_guard
    assert g.scale_for(1.0) == 1.0 and g.scale_for(g.stop) == 0.0
    assert g.scale_for((g.slow + g.stop) / 2) == pytest.approx(0.5)


def test_guard_stops_a_link_before_a_keepout_box_and_lets_it_back(box_guard):
    """Turning the base swings the wrist into a keep-out box that the TCP never comes near: the workspace
    layer cannot see it, the collision guard stops the arm before contact, and it may move away again."""
    lim, guard = box_guard
    filt = SafetyFilter(lim, collision=guard)
    target = HOME.copy()
    target[0] += 1.2
    res = run_stream(filt, HOME, [Command(q=target, command_time=k * filt.dt) for k in range(2500)])
    assert not check_stream(res.q, filt.dt, lim, filt.fk, filt.workspace)
    clear = [_clearance(guard, q, "safety/keepout0") for q in res.q[::2]]
    assert min(clear) >= 0.5 * lim.collision.stop_distance  # stopped before contact
    assert np.all(res.q[-1] == res.q[-2]) and res.q[-1, 0] < target[0] - 0.5  # at rest, short of the target
    assert any(e.kind == "collision_stop" for e in res.events)
    back = run_stream(filt, res.q[-1], [Command(q=HOME, command_time=(2500 + k) * filt.dt) for k in range(2500)],
                      t0=2500 * filt.dt)
    assert np.abs(back.q[-1] - HOME).max() == 0.0


def test_guard_stops_the_wrist_before_the_table(table_guard):
    """Gripper pointing up, TCP commanded down: the fingers stay high, the wrist links would hit the table
    first; the guard stops them above it (slowing down on the way)."""
    from sim.kinematics import Kinematics
    from sim.robot import TCP_OFFSET_Z

    lim, guard = table_guard
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.45, 0.45)
    q0 = kin.ik(T, np.array([-1.57, -1.0, 1.5, 0.6, -1.57, 0.0]))
    filt = SafetyFilter(lim, collision=guard)
    cmds, q = [], q0
    for k in range(3000):  # straight down at 0.1 m/s to 5 cm above the table
        T[2, 3] = max(0.05, 0.45 - 0.1 * k * filt.dt)
        q = kin.ik(T, q)
        cmds.append(Command(q=q, command_time=k * filt.dt))
    res = run_stream(filt, q0, cmds)
    assert not check_stream(res.q, filt.dt, lim, filt.fk, filt.workspace)
    clear = [_clearance(guard, x, TABLE_GEOM, fingers=False) for x in res.q[::5]]
    assert min(clear) >= 0.5 * lim.collision.stop_distance
    z_end = filt.fk.pose(list(res.q[-1]))[2]
    assert z_end > 0.15  # the TCP stopped high: the wrist, not the workspace, was the limit
    kinds = {e.kind for e in res.events}
    assert "collision_stop" in kinds and "collision" in kinds


def test_guard_stop_brakes_every_joint_by_the_stop_policy(table_guard):
    """A joint stream recorded from a policy episode on the sim twin (seed 100014 of the shipped bundle, 0.6 s
    from rest, 500 Hz): the shoulder lift swings at 0.8 rad/s while the elbow folds the wrist onto the shoulder.
    The guard predicts each joint braking on its own; tracking at zero speed instead scaled all joints by one
    factor, so the elbow ran on while the shoulder braked and the links came to 1.4 mm (the full episode: a
    contact and a protective stop). Braking by the stop policy keeps the stop distance."""
    lim, guard = table_guard
    rec = np.load(Path(__file__).with_name("selfcollision_stream.npz"))
    filt = SafetyFilter(lim, collision=guard)
    res = run_stream(filt, rec["start"], [Command(q=q, command_time=k * filt.dt) for k, q in enumerate(rec["desired"])])
    assert not check_stream(res.q, filt.dt, lim, filt.fk, filt.workspace)
    assert any(e.kind == "collision_stop" for e in res.events)
    clear = min(guard.check(q, q).clearance_now for q in res.q)
    assert clear >= lim.collision.stop_distance
