"""Letting go at rest (ControllerConfig.release_max_speed): on the UR5e twin, an opening of the grasp that the
policy asks for while the arm travels waits until the measured TCP slows down (at most release_max_wait), so
the held block is let go where the motion ends; off, it is let go mid-way. The loop's TCP speed is the
measured one."""

from __future__ import annotations

import numpy as np
import pytest
from sim_hands import hand_a_block_to_the_fingers
from test_controller_sim import chunk, make

from runtime.controller import ControllerConfig
from runtime.controller.gripper import GripperChannel
from safety import default_limits
from safety.events import EventCoalescer
from sim.build import build_world
from sim.twins.rig import SimRig

TRAVEL = np.array([0.15, 0.0, 0.0])  # m, in 1 s, peak speed ~0.23 m/s
START, MOVE, ASK_OPEN = 0.4, 1.0, 0.5  # s after the start: the move begins, lasts, the policy asks to open


def _smooth(tau):
    tau = np.clip(tau, 0.0, 1.0)
    return tau * tau * tau * (10 - 15 * tau + 6 * tau * tau)


def _carry_and_open(**cfg):
    """Close on a block, carry it 15 cm; the policy asks to open 0.5 s into the 1-s move (~0.2 m/s). Returns
    (seconds after the start at which the fingers were commanded open, TCP position then, end of the line,
    per-cycle (measured speed the loop computed, speed from the TCP positions), the loop's events)."""
    rig, loop, p0, R = make(reopen_empty_grasp=False, **cfg)
    rig.gripper.activate()
    hand_a_block_to_the_fingers(rig)
    t0 = rig.now_ns() * 1e-9
    path = lambda t: p0 + TRAVEL * _smooth((t - t0 - START) / MOVE)  # noqa: E731
    grip = lambda t: 0.0 if t >= t0 + START + ASK_OPEN else 1.0  # noqa: E731
    opened_at = opened_tcp = None
    speeds, prev = [], None
    for k in range(round(2.5 / rig.control_period)):
        if k % round(0.1 / rig.control_period) == 0:
            assert loop.submit(chunk(rig.now_ns(), path, R, grip))
        loop.cycle()
        measured = loop._tcp_speed()
        rig.step(1)
        s = rig.arm.state()
        if prev is not None:
            speeds.append((measured, np.linalg.norm(s.tcp_pose[:3] - prev) / rig.control_period))
        prev = s.tcp_pose[:3].copy()
        if opened_at is None and rig.gripper.state().target == 0.0 and k > 10:
            opened_at, opened_tcp = s.timestamp_ns * 1e-9 - t0, s.tcp_pose[:3].copy()
    return opened_at, opened_tcp, p0 + TRAVEL, np.array(speeds), loop.drain_events()


def test_an_opening_while_carrying_waits_for_the_arm_to_come_to_rest():
    asked = START + ASK_OPEN
    at, tcp, end, _, events = _carry_and_open(release_max_speed=0.03)
    assert at is not None and at > asked + 0.1  # held past the policy's ask...
    assert at < START + MOVE + 0.5  # ...only until the arm slowed down at the line's end
    assert np.linalg.norm(tcp - end) < 0.01  # so the block is let go where the motion ends
    held = [e for e in events if e.kind == "gripper_release_held"]
    assert held and "TCP speed" in held[0].message

    at_off, tcp_off, _, _, events_off = _carry_and_open()  # off: let go where the policy asked, mid-way
    assert at_off == pytest.approx(asked, abs=0.05)
    assert np.linalg.norm(tcp_off - end) > 0.02
    assert not [e for e in events_off if e.kind == "gripper_release_held"]


def test_the_loop_measures_the_tcp_speed_from_the_joints():
    _, _, _, speeds, _ = _carry_and_open()
    moving = speeds[:, 1] > 0.05
    assert moving.sum() > 100 and speeds[:, 1].max() > 0.15
    # the Jacobian's speed at the cycle against the TCP's finite difference over the next step
    assert np.median(np.abs(speeds[moving, 0] - speeds[moving, 1]) / speeds[moving, 1]) < 0.05


def test_the_wait_ends_after_release_max_wait_and_never_holds_an_empty_reopen():
    rig = SimRig(build_world("pick_place", seed=2, dr="off", fidelity="fast"), "lockstep")
    rig.gripper.activate()
    cfg = ControllerConfig(release_max_speed=0.03, release_max_wait=0.3, reopen_empty_grasp=False)
    channel = GripperChannel(rig.gripper, default_limits("ur5e"), cfg, tcp_speed=lambda: 0.5)  # always fast
    events = EventCoalescer(0.1)
    period = rig.control_period

    def feed(value, seconds):
        sent = []
        for _ in range(round(seconds / period)):
            sent.append(channel.update(value, rig.now_ns() * 1e-9, True, events))
            rig.step(1)
        return sent

    feed(0.0, 0.1)
    assert True in feed(1.0, 0.2)  # closing is never held
    sent = feed(0.0, 0.6)
    first = sent.index(False)  # the open went out once the wait ran out, while still "moving"
    assert first * period == pytest.approx(0.3, abs=2 * period)
    assert any(e.kind == "gripper_release_held" for e in events.flush(10.0))
    feed(1.0, 0.3)  # the policy changes its mind mid-wait: the next ask waits afresh
    sent = feed(0.0, 0.2) + feed(1.0, 0.01) + feed(0.0, 0.2)
    assert False not in sent  # neither 0.2-s ask reached 0.3 s
