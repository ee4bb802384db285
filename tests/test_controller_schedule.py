"""Chunk scheduling, latency compensation, blending and chunk rejection, on a perfect-tracking fake arm.

The fake arm reaches every servo_j target at once, so these tests see the controller's own output (the
planned stream before safety, and the filter's verdict on it) without simulator dynamics.
"""

from __future__ import annotations

import numpy as np
import pytest

from runtime.controller import ControllerConfig, ControllerLoop
from runtime.controller.ik_follow import branch_of
from runtime.messages import ActionChunk
from safety import SafetyFilter, default_limits
from sim.devices import ArmState, SafetyMode
from sim.kinematics import Kinematics
from sim.robot import TCP_OFFSET_Z, get_variant

DT = 0.002
HOME = np.array(get_variant("ur5e").home)
KIN = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
LIMITS = default_limits("ur5e")


class FakeArm:
    control_period = DT

    def __init__(self, q):
        self.q, self.qd = np.array(q, float), np.zeros(6)
        self.t_ns = 1_000_000_000
        self.sent = 0

    def init_period(self):
        return self.t_ns

    def wait_period(self, t_start_ns):
        self.t_ns = t_start_ns + int(DT * 1e9)

    def state(self):
        return ArmState(self.q.copy(), self.qd.copy(), np.zeros(6), self.q.copy(), self.t_ns,
                        safety_mode=self.mode)

    mode = SafetyMode.NORMAL

    def servo_j(self, q, *args):
        if self.mode != SafetyMode.NORMAL:
            return False
        self.qd = (np.asarray(q) - self.q) / DT
        self.q = np.array(q, float)
        self.sent += 1
        return True

    def servo_stop(self, deceleration=10.0):
        self.qd[:] = 0.0

    def unlock_protective_stop(self):
        return True


def _loop(q0=HOME, collision=False, **cfg):
    arm = FakeArm(q0)
    return ControllerLoop(arm, None, SafetyFilter(LIMITS, collision=collision), ControllerConfig(**cfg)), arm


def _step(loop, arm, n=1):
    out = []
    for _ in range(n):
        out.append(loop.cycle())
        arm.wait_period(arm.t_ns)
    return out


def _ee_chunk(t_first_ns, q_ref, shift_fn, n=16, gap_ns=100_000_000, obs_ns=None):
    """EE chunk: the TCP of q_ref moved by shift_fn(t_s) (metres, base frame) at each action time."""
    T = KIN.fk(q_ref)
    times = t_first_ns + gap_ns * np.arange(n)
    acts = [np.concatenate([T[:3, 3] + shift_fn(t * 1e-9), T[:3, 0], T[:3, 1], [0.0]]) for t in times]
    return ActionChunk(actions=np.array(acts), times_ns=times.astype(np.int64),
                       obs_time_ns=int(times[0] if obs_ns is None else min(obs_ns, times[0])))


def _joint_chunk(t_first_ns, qs, gap_ns=100_000_000):
    times = (t_first_ns + gap_ns * np.arange(len(qs))).astype(np.int64)
    acts = np.hstack([np.asarray(qs, float), np.zeros((len(qs), 1))])
    return ActionChunk(actions=acts, times_ns=times, obs_time_ns=int(times[0]), kind="joint")


def test_past_actions_are_dropped_but_the_last_one_anchors():
    loop, arm = _loop(execution_latency=0.02)
    _step(loop, arm)
    now = arm.t_ns
    qs = HOME + np.outer(np.arange(10) * 0.01, [1, 0, 0, 0, 0, 0])
    # actions at now - 0.35, -0.25, -0.15, -0.05, +0.05 ... s: the first four are past (now + 20 ms)
    assert loop.submit(_joint_chunk(now - 350_000_000, qs))
    _step(loop, arm)
    assert loop.timeline.last_dropped == 3
    assert loop.timeline.traj.new.times[0] == pytest.approx((now - 50_000_000) * 1e-9)  # the anchor
    assert any(e.kind == "chunk_late" for e in loop.drain_events())
    # a chunk entirely in the past is rejected as stale
    assert not loop.submit(_joint_chunk(arm.t_ns - 2_000_000_000, qs[:3]))
    assert [e.kind for e in loop.drain_events()] == ["chunk_stale"]


def test_latency_compensation_commands_targets_early_by_the_configured_amount():
    qs = HOME + np.outer(np.sin(np.arange(16) * 0.3) * 0.05, [1, -0.5, 0.5, 0, 1, 0])
    streams = {}
    for lat in (0.0, 0.06):
        loop, arm = _loop(execution_latency=lat)
        _step(loop, arm)
        loop.submit(_joint_chunk(arm.t_ns + 200_000_000, qs))
        streams[lat] = np.array([r.desired for r in _step(loop, arm, 700)])
    shift = int(round(0.06 / DT))
    # the same plan, 30 cycles earlier: desired_L(t) == desired_0(t + L)
    np.testing.assert_allclose(streams[0.06][:-shift], streams[0.0][shift:], atol=1e-9)
    assert np.max(np.abs(streams[0.06][300] - streams[0.0][300])) > 1e-3  # and it really differs


def test_overlapping_chunks_with_offsets_blend_without_jumps_and_pass_safety():
    loop, arm = _loop(collision=True)
    _step(loop, arm)
    t0 = arm.t_ns * 1e-9
    line = lambda t: np.array([0.1 * max(0.0, t - t0 - 0.1), 0.0, 0.0])  # noqa: E731  0.1 m/s along x
    des, modes, naive = [], [], []
    for k in range(8):  # a new chunk every 0.3 s, each disagreeing with the last by 4 mm
        off = np.array([0.0, 0.004 if k % 2 else -0.004, 0.002 * (k % 3 - 1)])
        old = loop.timeline.traj
        assert loop.submit(_ee_chunk(arm.t_ns, HOME, lambda t: line(t) + off))
        for i in range(150):
            r = _step(loop, arm)[0]
            des.append(r.desired)
            modes.append(r.result.mode)
            if i == 0 and old is not None:  # what switching without a blend would have jumped by
                te = r.now + loop.execution_latency
                naive.append(np.max(np.abs(loop.timeline.traj.new.eval(te)[0] - old.eval(te)[0])))
    des = np.array(des)
    v = np.diff(des, axis=0) / DT
    a = np.diff(v, axis=0) / DT
    j = np.diff(a, axis=0) / DT
    J = LIMITS.joints
    assert np.all(np.abs(v).max(0) <= np.array(J.velocity))
    assert np.all(np.abs(a).max(0) <= np.array(J.acceleration))
    assert np.all(np.abs(j).max(0) <= np.array(J.jerk))
    step = np.abs(np.diff(des, axis=0)).max()
    assert step < 0.2 * min(naive), f"per-cycle step {step:.2e} rad vs naive switch {min(naive):.2e} rad"
    pass_frac = np.mean(np.array(modes) == "pass")
    assert pass_frac > 0.95, pass_frac


def test_unreachable_chunk_is_rejected_and_the_old_tail_kept():
    loop, arm = _loop()
    _step(loop, arm)
    good = _ee_chunk(arm.t_ns, HOME, lambda t: np.array([0.02 * (t - 1.0), 0.0, 0.0]))
    assert loop.submit(good)
    ref, ref_arm = _loop()
    _step(ref, ref_arm)
    ref.submit(good)
    _step(loop, arm, 50)
    _step(ref, ref_arm, 50)
    far = _ee_chunk(arm.t_ns, HOME, lambda t: np.array([1.5, 0.0, 0.0]))  # 1.5 m away: out of reach
    assert not loop.submit(far)
    ev = loop.drain_events()
    assert [e.kind for e in ev] == ["chunk_unreachable"] and "no IK solution" in ev[0].message
    a = np.array([r.desired for r in _step(loop, arm, 200)])
    b = np.array([r.desired for r in _step(ref, ref_arm, 200)])
    np.testing.assert_allclose(a, b, atol=1e-12)  # exactly the old plan


def test_branch_jumping_chunk_is_rejected():
    q_a = HOME.copy()
    q_a[4] = -0.2  # wrist branch 1 (sin q5 < 0), near the wrist singularity
    q_b = q_a.copy()
    q_b[4] = +0.2  # a nearby pose whose nearest IK solution is on the other wrist branch
    assert branch_of(KIN, q_a) != branch_of(KIN, q_b)
    loop, arm = _loop(q0=q_a)
    _step(loop, arm)
    Ta, Tb = KIN.fk(q_a), KIN.fk(q_b)
    times = arm.t_ns + 100_000_000 * np.arange(10)
    acts = [np.concatenate([T[:3, 3], T[:3, 0], T[:3, 1], [0.0]]) for T in [Ta] * 5 + [Tb] * 5]
    chunk = ActionChunk(actions=np.array(acts), times_ns=times.astype(np.int64), obs_time_ns=int(times[0]))
    assert not loop.submit(chunk)
    ev = loop.drain_events()
    assert [e.kind for e in ev] == ["chunk_branch_jump"] and "action 5" in ev[0].message
    # a joint chunk that swings a joint faster than jump_factor x its velocity limit is rejected too
    qs = np.array([q_a] * 3 + [q_a + [0, 0, 0, 0, 0, 2.0]] * 3)
    assert not loop.submit(_joint_chunk(arm.t_ns, qs))
    assert [e.kind for e in loop.drain_events()] == ["chunk_joint_jump"]
    assert not loop.timeline.active  # nothing was adopted: the arm holds


def test_controller_refuses_mismatched_variant():
    with pytest.raises(ValueError, match="control period"):
        ControllerLoop(FakeArm(HOME), None, SafetyFilter(default_limits("ur5"), collision=False))


def test_latency_is_estimated_by_cross_correlation_and_adapted_smoothly():
    # the fake arm reaches each target one cycle after it is sent: a pure 2 ms execution latency
    loop, arm = _loop(execution_latency=0.03, adapt_latency=True, latency_slew=0.05, latency_window=0.5)
    _step(loop, arm)
    qs = HOME + np.outer(np.sin(np.arange(30) * 0.4) * 0.1, [1, 0.5, -0.5, 1, 0, 1])
    loop.submit(_joint_chunk(arm.t_ns, qs))
    lat = [loop.execution_latency]
    for _ in range(1200):
        _step(loop, arm)
        lat.append(loop.execution_latency)
    assert loop.latency_estimate() == pytest.approx(DT, abs=2e-4)
    assert lat[-1] == pytest.approx(DT, abs=5e-4)
    assert np.max(np.abs(np.diff(lat))) <= 0.05 * DT + 1e-12  # slew-limited: the sampling time never jumps


def test_every_command_is_the_filters_output_and_ready_after_the_first_cycle():
    loop, arm = _loop()
    sent = []
    servo_j = arm.servo_j
    arm.servo_j = lambda q, *a: sent.append(np.array(q)) or servo_j(q, *a)
    assert not loop.ready
    results = _step(loop, arm)
    assert loop.ready
    loop.submit(_joint_chunk(arm.t_ns, HOME + np.outer(np.arange(8) * 0.02, np.ones(6))))
    results += _step(loop, arm, 400)
    assert len(sent) == len(results)
    for q, r in zip(sent, results):
        assert np.array_equal(q, r.result.q)


def test_a_crashing_cycle_ends_in_the_controlled_stop():
    loop, arm = _loop()
    loop.submit(_joint_chunk(arm.t_ns + 2_000_000, HOME + np.outer(np.arange(16) * 0.02, np.ones(6))))
    loop.run(cycles=300)  # paced by init_period / wait_period (the fake advances its clock)
    assert np.max(np.abs(arm.qd)) > 0.05
    sample = loop.timeline.sample

    def broken(t):
        raise RuntimeError("bug")
    loop.timeline.sample = broken
    loop.run(cycles=10)
    loop.timeline.sample = sample
    kinds = [e.kind for e in loop.drain_events()]
    assert "controller_error" in kinds  # the crash was caught, then the stop ran through the filter
    assert loop.stopped and np.max(np.abs(arm.qd)) < 2e-3


def test_robot_side_stops_drop_the_plan_and_a_robot_estop_latches_ours():
    loop, arm = _loop()
    loop.submit(_joint_chunk(arm.t_ns, HOME + np.outer(np.arange(16) * 0.02, np.ones(6))))
    _step(loop, arm, 100)
    arm.mode = SafetyMode.SAFEGUARD_STOP
    res = _step(loop, arm, 20)
    assert not any(r.sent for r in res) and not loop.timeline.active
    arm.mode = SafetyMode.NORMAL
    _step(loop, arm, 5)
    kinds = [e.kind for e in loop.drain_events()]
    assert "robot_halted" in kinds and "robot_resumed" in kinds and "plan_dropped" in kinds
    assert loop.state == "holding"  # no motion until a new chunk
    arm.mode = SafetyMode.ROBOT_EMERGENCY_STOP
    _step(loop, arm, 3)
    arm.mode = SafetyMode.NORMAL
    _step(loop, arm, 3)
    assert loop.state == "estop"  # latched: released on the robot is not enough
    assert loop.reset_estop("operator-7") and loop.state == "holding"
