"""The safety filter in closed loop with the sim arm: hostile command streams never reach the table.

A "policy" sends adversarial joint targets at the control rate; each cycle the filter turns them into a safe
target, the SimArm servos to it (servo_j, as the runtime does) and physics runs. The arm must never
protectively stop (it never touches anything), must stay above the table and inside its joint speed limits,
and must come to rest when the commands stop arriving.
"""

from __future__ import annotations

import numpy as np
import pytest

from safety import SafetyFilter, default_limits
from sim.build import build_world
from sim.kinematics import Kinematics
from sim.robot import TCP_OFFSET_Z
from sim.twins.rig import SimRig

CYCLES = 600  # 1.2 s at 500 Hz


def _rig():
    return SimRig(build_world("pick_place", seed=2, dr="off", fidelity="fast"), "lockstep")


def _run(rig, desired_at, fresh_until=None):
    """Closed loop; returns (tcp z min, max measured |qd| / limit, protective stop seen, final |qd|)."""
    limits = default_limits("ur5e")
    filt = SafetyFilter(limits, collision=True)
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    vmax = np.asarray(limits.joints.velocity)
    arm = rig.arm
    period = arm.control_period
    z_min, speed_ratio, stopped = np.inf, 0.0, False
    last_command_time = 0.0
    for k in range(CYCLES):
        now = k * period
        s = arm.state()
        stopped |= s.is_protective_stopped
        if fresh_until is None or now < fresh_until:
            last_command_time = now
        r = filt.step(desired_at(k, s.q), s.q, s.qd, now, last_command_time)
        arm.servo_j(r.q, 0.5, 0.5, period, 0.03, 2000)
        rig.step(1)
        z_min = min(z_min, kin.fk(s.q)[2, 3])
        speed_ratio = max(speed_ratio, float(np.max(np.abs(s.qd) / vmax)))
    return z_min, speed_ratio, stopped, float(np.max(np.abs(arm.state().qd)))


def _down_into_table(q_home):
    """A target 40 cm below the table straight under the current TCP, reached by a huge joint jump."""
    kin = Kinematics.with_tcp_z("ur5e", TCP_OFFSET_Z)
    T = kin.fk(q_home)
    T[2, 3] = -0.4
    T[0, 3] += 0.05
    # IK cannot reach below the table with the gripper down; extrapolate the joint motion instead.
    T_low = kin.fk(q_home)
    T_low[2, 3] = 0.02
    q_low = kin.ik(T_low, q_home)
    return q_home + 4.0 * (q_low - q_home)


def test_dive_into_the_table_is_stopped_above_it():
    rig = _rig()
    q0 = rig.arm.state().q
    target = _down_into_table(q0)
    z_min, speed_ratio, stopped, _ = _run(rig, lambda k, q: target)
    assert not stopped, "the arm touched something: the filter let a collision through"
    assert z_min > 0.0
    assert speed_ratio <= 1.05


def test_nan_bursts_and_jumps_are_held_or_limited():
    rig = _rig()
    q0 = rig.arm.state().q
    rng = np.random.default_rng(0)

    def hostile(k, q):
        if k % 50 < 5:
            return np.full(6, np.nan)
        if k % 50 < 10:
            return q0 + rng.uniform(-3, 3, 6)
        return q0 + 0.3 * np.sin(k * 0.5)  # oscillation at the control rate
    z_min, speed_ratio, stopped, _ = _run(rig, hostile)
    assert not stopped and z_min > 0.0 and speed_ratio <= 1.05


@pytest.mark.parametrize("fresh_for", [0.2, 0.5])
def test_stale_commands_bring_the_arm_to_rest(fresh_for):
    rig = _rig()
    q0 = rig.arm.state().q
    sweep = q0 + np.array([0.6, -0.2, 0.3, 0.0, 0.0, 0.5])
    _, _, stopped, final_speed = _run(rig, lambda k, q: sweep, fresh_until=fresh_for)
    assert not stopped
    assert final_speed < 1e-2, "the watchdog must stop the arm when commands go stale"
