"""Scenario tests of the sim twins: a grasp that survives shaking, a protective stop against the table (and none
for a graze), the realtime physics thread, and lock-step determinism.

Motions are computed with MuJoCo itself (damped least squares on the "tcp" site with mj_jacSite), so these
tests do not depend on the analytic IK module.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before the first mujoco import: headless rendering

import threading  # noqa: E402
import time  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from sim.devices import SafetyMode  # noqa: E402
from sim.objects import Placement, add_block  # noqa: E402
from sim.scene import base_scene  # noqa: E402
from sim.twins import ArmNoiseConfig, CameraNoiseConfig, SimRig  # noqa: E402
from sim.twins.arm import matrix_to_rotvec  # noqa: E402
from sim.world import World  # noqa: E402

BLOCK_HALF = 0.0225  # a 4.5 cm cube
BLOCK_MASS = 0.15  # kg, the heavy end of the task objects
BLOCK_XY = (-0.13, 0.50)  # under the TCP's home position


def make_world(block: bool = True) -> World:
    spec = base_scene()
    if block:
        add_block(spec, "block", [BLOCK_HALF] * 3, [0.8, 0.2, 0.2, 1.0], Placement(*BLOCK_XY), mass=BLOCK_MASS)
    return World(spec.compile())


class TcpIK:
    """Damped-least-squares IK on the world's tcp site, on a scratch MjData (the live data is untouched)."""

    def __init__(self, world: World):
        self.w, self.m = world, world.model
        self.d = mujoco.MjData(world.model)
        self.jp, self.jr = np.zeros((3, self.m.nv)), np.zeros((3, self.m.nv))

    def solve(self, q0, pos, R, iters: int = 100, tol: float = 1e-9) -> np.ndarray:
        q = np.array(q0, dtype=float)
        for _ in range(iters):
            self.d.qpos[self.w.arm_qpos_adr] = q
            mujoco.mj_kinematics(self.m, self.d)
            mujoco.mj_comPos(self.m, self.d)
            site = self.w.tcp_site
            err = np.concatenate([np.asarray(pos) - self.d.site_xpos[site],
                                  matrix_to_rotvec(R @ self.d.site_xmat[site].reshape(3, 3).T)])
            if err @ err < tol**2:
                break
            mujoco.mj_jacSite(self.m, self.d, self.jp, self.jr, site)
            J = np.vstack([self.jp[:, self.w.arm_dof_adr], self.jr[:, self.w.arm_dof_adr]])
            q += J.T @ np.linalg.solve(J @ J.T + 1e-6 * np.eye(6), err)
        return q


def servo_line(rig: SimRig, ik: TcpIK, q, p0, p1, R, duration: float, each_cycle=None, gain: float = 1000.0,
               lookahead: float = 0.05) -> np.ndarray:
    """Stream servo_j along a straight TCP line with a smooth-step time law (zero speed at both ends)."""
    n = max(1, int(round(duration / rig.control_period)))
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    for k in range(1, n + 1):
        s = k / n
        s = s * s * (3 - 2 * s)
        q = ik.solve(q, p0 + s * (p1 - p0), R, iters=10)
        assert rig.arm.servo_j(q, time=rig.control_period, lookahead_time=lookahead, gain=gain)
        rig.step(1)
        if each_cycle is not None:
            each_cycle()
    return q


def _pose(world: World, body: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = world.data.xmat[body].reshape(3, 3)
    T[:3, 3] = world.data.xpos[body]
    return T


def test_grasp_survives_lift_and_shake():
    world = make_world()
    rig = SimRig(world)
    arm, gripper, ik = rig.arm, rig.gripper, TcpIK(world)
    block = world.model.body("block").id
    R_down = world.tcp_pose()[:3, :3].copy()  # home: TCP z axis pointing down, fingers closing along x
    bx, by = world.data.xpos[block][:2]
    above, grasp = np.array([bx, by, 0.15]), np.array([bx, by, BLOCK_HALF])

    q = ik.solve(arm.state().q, above, R_down)
    assert arm.move_j(q, speed=1.5, acceleration=3.0)
    q = servo_line(rig, ik, q, above, grasp, R_down, 1.0)
    rig.step(100)
    gripper.activate()
    assert gripper.close(speed=1.0, force=1.0)
    st = gripper.state()
    assert st.object_detected and not st.is_moving and 0.2 < st.position < 0.8, st

    rel0 = np.linalg.inv(world.tcp_pose()) @ _pose(world, block)
    worst = [0.0]

    def track():
        rel = np.linalg.inv(world.tcp_pose()) @ _pose(world, block)
        worst[0] = max(worst[0], float(np.linalg.norm(rel[:3, 3] - rel0[:3, 3])))

    lifted = grasp + [0, 0, 0.20]
    q = servo_line(rig, ik, q, grasp, lifted, R_down, 1.0, track)
    assert world.data.xpos[block][2] > BLOCK_HALF + 0.18

    # Shake: shoulder pan, shoulder lift and the three wrists, ±0.1 rad at 1.5 Hz for 2 s, tight servo.
    q_lift = q.copy()
    mask = np.array([1, 1, 0, 1, 1, 1.0])
    for k in range(int(2.0 / rig.control_period)):
        t = k * rig.control_period
        assert arm.servo_j(q_lift + 0.1 * np.sin(2 * np.pi * 1.5 * t) * mask, time=rig.control_period,
                           lookahead_time=0.03, gain=2000)
        rig.step(1)
        track()
    # Fast translations: 12 cm moves in 0.25 s (peak ~0.7 m/s, ~11 m/s^2), in x, y and z.
    p = world.tcp_pose()[:3, 3].copy()
    waypoints = [p, p + [0.12, 0, 0], p - [0.12, 0, 0], p + [0, 0.12, 0.05], p - [0, 0.1, 0], p]
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        q = servo_line(rig, ik, q, a, b, R_down, 0.25, track, gain=2000, lookahead=0.03)
    rig.step(50)
    track()

    assert not rig.protective_stopped, rig.stop_reason
    print(f"block drift relative to the TCP: max {worst[0] * 1e3:.2f} mm")
    assert worst[0] < 0.01, f"block moved {worst[0] * 1e3:.1f} mm relative to the TCP"
    assert gripper.state().object_detected
    assert world.data.xpos[block][2] > 0.15  # still up in the air


def test_protective_stop_on_table_contact_holds_and_recovers():
    world = make_world(block=False)
    rig = SimRig(world)
    arm, ik = rig.arm, TcpIK(world)
    R_down = world.tcp_pose()[:3, :3].copy()
    start = world.tcp_pose()[:3, 3].copy()
    q = arm.state().q
    # Drive the TCP straight down, 10 cm below the table top, at ~0.2 m/s.
    n = int(1.8 / rig.control_period)
    for k in range(1, n + 1):
        q = ik.solve(q, start + [0, 0, -(start[2] + 0.10) * k / n], R_down, iters=10)
        if not arm.servo_j(q, time=rig.control_period, lookahead_time=0.05, gain=1000):
            break
        rig.step(1)
    state = arm.state()
    assert state.is_protective_stopped and state.safety_mode == SafetyMode.PROTECTIVE_STOP
    assert "table" in rig.stop_reason
    assert state.tcp_pose[2] > -0.005  # stopped at first touch, not pushed through the table
    q_stop = state.q
    rig.step(int(1.0 / rig.control_period))
    assert np.max(np.abs(arm.state().q - q_stop)) < 2e-3  # held in place
    assert not arm.speed_j(np.zeros(6)) and not arm.move_j(q_stop)
    assert not arm.unlock_protective_stop()
    rig.sleep(3.9)  # 4.9 s after the stop
    assert not arm.unlock_protective_stop()
    rig.sleep(0.2)
    assert arm.unlock_protective_stop()
    assert arm.state().safety_mode == SafetyMode.NORMAL
    up = ik.solve(arm.state().q, arm.state().tcp_pose[:3] + [0, 0, 0.1], R_down)
    assert arm.move_j(up)  # the contact present at unlock is forgiven until it separates
    assert not rig.protective_stopped and arm.state().tcp_pose[2] > 0.09


def test_a_graze_on_the_table_is_not_a_stop_but_pressing_on_is():
    world = make_world(block=False)
    rig = SimRig(world)
    arm, ik, m = rig.arm, TcpIK(world), world.model
    R_down = world.tcp_pose()[:3, :3].copy()
    x, y, z = world.tcp_pose()[:3, 3]
    table = m.geom("table").id

    def table_force() -> float:
        d, f6, worst = world.data, np.zeros(6), 0.0
        for i in range(d.ncon):
            g = d.contact.geom[i]
            if table in g and rig.geom_robot[g].any():
                mujoco.mj_contactForce(m, d, i, f6)
                worst = max(worst, abs(f6[0]))
        return worst

    def servo(z_cmd: float, q):
        q = ik.solve(q, [x, y, z_cmd], R_down, iters=10)
        assert arm.servo_j(q, time=rig.control_period, lookahead_time=0.05, gain=1000)
        rig.step(1)
        return q

    q = arm.state().q
    while table_force() == 0.0:  # descend at 2 cm/s until the fingers first touch the table
        z -= 0.02 * rig.control_period
        assert z > -0.02, "never touched the table"
        q = servo(z, q)
    worst = 0.0
    for _ in range(int(1.0 / rig.control_period)):  # hold there for a second: a light, lasting contact
        q = servo(z, q)
        worst = max(worst, table_force())
    assert 0.0 < worst < rig.safety.force_limit_n and not rig.protective_stopped, rig.stop_reason
    z_touch = z
    for _ in range(int(2.0 / rig.control_period)):  # now press on at 2 cm/s (the open fingers splay first)
        z -= 0.02 * rig.control_period
        if not arm.servo_j(ik.solve(q, [x, y, z], R_down, iters=10), time=rig.control_period,
                           lookahead_time=0.05, gain=1000):
            break
        rig.step(1)
    assert rig.protective_stopped and "contact force" in rig.stop_reason and "table" in rig.stop_reason
    assert arm.state().tcp_pose[2] > z_touch - 0.03


def test_self_collision_and_force_rules_classify_geoms():
    rig = SimRig(make_world())
    m = rig.world.model
    pads = [m.geom(n).id for n in ("gripper/left_pad1", "gripper/right_pad2")]
    assert rig.geom_pad[pads].all() and rig.geom_robot[pads].all()
    for static in ("table", "floor"):
        assert not rig.geom_robot[m.geom(static).id] and not rig.geom_movable[m.geom(static).id]
    assert rig.geom_movable[m.geom("block/geom").id] and not rig.geom_robot[m.geom("block/geom").id]
    rig.step(200)  # resting at home: no spurious stop from the block on the table or the closed linkage
    assert not rig.protective_stopped


def test_realtime_rate_and_clean_shutdown():
    rig = SimRig(make_world(block=False), mode="realtime")
    with pytest.raises(RuntimeError):
        rig.step(1)
    with rig:
        time.sleep(0.5)
        rate = rig.achieved_rate_hz()
        q = rig.arm.state().q
        goal = q + np.array([0.1, -0.05, 0.05, 0.1, 0.1, 0.1])
        t0 = time.monotonic()
        assert rig.arm.move_j(goal, speed=1.0, acceleration=4.0)
        assert time.monotonic() - t0 > 0.1  # it really took wall-clock time
        s1, s2 = rig.arm.state(), rig.arm.state()
        assert s2.timestamp_ns >= s1.timestamp_ns and abs(s1.timestamp_ns - time.monotonic_ns()) < 1e8
    assert rate > 300, f"physics ran at {rate:.0f} Hz"
    assert not rig.running
    assert not any(t.name == "sim-rig-physics" for t in threading.enumerate())
    assert rig.error is None


def test_realtime_camera_renders_in_its_own_thread():
    rig = SimRig(make_world(block=False), mode="realtime")
    with rig:
        cam = rig.camera("scene_cam", 64, 48, fps=10, noise=CameraNoiseConfig(shadows=False, latency_s=0.02))
        cam.start()
        f1 = cam.read(timeout_s=20.0)  # first frame includes creating the GL context
        f2 = cam.read(timeout_s=5.0)
        assert f2.seq > f1.seq and f2.capture_ns > f1.capture_ns
        assert cam.read_latest(max_age_s=5.0).seq >= f2.seq
    assert cam._thread is None and cam.error is None
    assert not any(t.name.startswith("sim-camera") for t in threading.enumerate())


def test_lockstep_is_deterministic_with_seeded_noise():
    def run():
        rig = SimRig(make_world(), arm_noise=ArmNoiseConfig(q_std=1e-4, qd_std=1e-3, seed=7))
        q = rig.arm.state().q
        rig.arm.speed_j([0.2, -0.1, 0.1, 0, 0, 0.3], acceleration=2.0, time=0.3)
        rig.step(300)
        rig.gripper.activate()
        rig.gripper.move(0.5, speed=1.0, force=0.3)
        rig.arm.move_j(q)
        s = rig.arm.state()
        return np.concatenate([s.q, s.qd, [s.timestamp_ns, rig.gripper.state().position]]), rig.world.data.qpos.copy()

    (a, qa), (b, qb) = run(), run()
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(qa, qb)


def test_servo_gain_and_lookahead_set_tracking_tightness():
    def lag(gain, lookahead):
        rig = SimRig(make_world(block=False))
        q0 = rig.arm.state().q
        for k in range(250):
            rig.arm.servo_j(q0 + 0.3 * k / 250 * np.array([1, 0, 0, 0, 0, 0]), time=rig.control_period,
                            lookahead_time=lookahead, gain=gain)
            rig.step(1)
        return abs(rig.arm.state().q[0] - (q0[0] + 0.3))

    assert lag(2000, 0.03) < lag(300, 0.1) < lag(100, 0.2)


def test_gripper_refuses_commands_before_activation():
    rig = SimRig(make_world(block=False))
    assert not rig.gripper.move(1.0)
    assert not rig.gripper.state().is_activated
    rig.gripper.activate()
    assert rig.gripper.move(0.5, wait=False) and rig.gripper.state().is_moving
