"""The gripper channel's closure bound, on the 2F-85 twin: never above the fingers' real closure (the safety
filter places the finger points for it), raised as a close is reported, down at once on an open, which is held
while the open fingers would reach into a keep-out box; the controller hands it to its filter every cycle."""

from __future__ import annotations

import numpy as np
import pytest
from sim_hands import hand_a_block_to_the_fingers

from runtime.controller import ControllerConfig, ControllerLoop
from runtime.controller.gripper import SETTLE_S, GripperChannel
from safety import SafetyFilter, default_limits
from safety.events import EventCoalescer
from sim.build import build_world
from sim.twins.rig import SimRig

LIMITS = default_limits("ur5e")
CFG = ControllerConfig(gripper_levels=(0.0, 0.5, 1.0), reopen_empty_grasp=False)


def _rig():
    rig = SimRig(build_world("pick_place", seed=2, dr="off", fidelity="fast"), "lockstep")
    rig.gripper.activate()
    return rig


def _feed(channel, rig, value, seconds, events=None):
    """Feed `value` every cycle for `seconds`; per cycle (bound, the fingers' measured closure)."""
    out = []
    for _ in range(round(seconds / rig.control_period)):
        channel.update(value, rig.now_ns() * 1e-9, True, events)
        rig.step(1)
        out.append((channel.closure_bound, rig.world.gripper_position()))
    return np.array(out)


@pytest.mark.parametrize("holding", [False, True])
def test_a_close_raises_the_bound_as_reported_and_never_past_the_fingers(holding):
    rig = _rig()
    if holding:
        hand_a_block_to_the_fingers(rig)
    channel = GripperChannel(rig.gripper, LIMITS, CFG)
    start = _feed(channel, rig, 0.0, 0.3)
    assert (start[:, 0] == 0.0).all()  # open: the first command only sets the state
    run = _feed(channel, rig, 1.0, 2.5)
    bound, real = run[:, 0], run[:, 1]
    assert (np.diff(bound) >= 0).all()  # a close only raises it
    assert (bound <= real + 1e-9).all()  # never past the fingers: the points always bound them
    assert (bound[: round(SETTLE_S / rig.control_period)] == 0.0).all()  # no report taken before the move
    if holding:  # stopped on the block: the bound is the block's width, not the command
        assert rig.gripper.state().object_detected
        assert 0.3 < bound[-1] < 0.9 and bound[-1] == pytest.approx(real[-1], abs=0.02)
    else:
        assert bound[-1] > 0.9


def test_an_open_takes_the_bound_down_at_once_and_is_held_near_a_box():
    rig = _rig()
    clear = {"ok": False}
    channel = GripperChannel(rig.gripper, LIMITS, CFG, may_open=lambda closure: clear["ok"])
    events = EventCoalescer(0.1)
    _feed(channel, rig, 0.0, 0.3)
    _feed(channel, rig, 0.5, 2.0)
    half = channel.closure_bound
    assert half == pytest.approx(0.5, abs=0.05)
    held = _feed(channel, rig, 0.0, 0.5, events)  # the filter says the open fingers would reach into a box
    assert (held[:, 0] == half).all() and rig.gripper.state().target == pytest.approx(0.5, abs=0.01)
    reported = [e for e in events.flush(10.0) if e.kind == "gripper_open_held"]
    assert reported and "keep-out box" in reported[0].message
    clear["ok"] = True  # the arm has moved clear
    opened = _feed(channel, rig, 0.0, 0.5, events)
    assert opened[0, 0] == 0.0 and opened[0, 1] > 0.4  # down on the command's cycle, before the fingers move
    assert rig.gripper.state().target == 0.0
    assert _feed(channel, rig, 1.0, 0.1)[-1, 0] == 0.0  # a close again: no report yet, still open


def test_held_back_by_a_box_the_fingers_open_as_far_as_it_allows_and_the_rest_once_clear():
    rig = _rig()
    allowed = {"from": 0.3}  # the boxes allow closures from this one up
    channel = GripperChannel(rig.gripper, LIMITS, CFG, may_open=lambda closure: closure >= allowed["from"] - 1e-9)
    events = EventCoalescer(0.1)
    _feed(channel, rig, 0.0, 0.3)
    _feed(channel, rig, 0.5, 2.0)
    part = _feed(channel, rig, 0.0, 1.0, events)  # the policy asks the fingers open
    assert part[0, 0] == pytest.approx(0.3) and rig.gripper.state().target == pytest.approx(0.3, abs=0.01)
    assert part[-1, 1] == pytest.approx(0.3, abs=0.05)  # they open that far, which lets go of what they held
    reported = [e for e in events.flush(10.0) if e.kind == "gripper_open_partial"]
    assert reported and "keep-out boxes" in reported[0].message
    allowed["from"] = 0.0  # the arm has moved clear
    rest = _feed(channel, rig, 0.0, 0.5)
    assert rest[0, 0] == 0.0 and rig.gripper.state().target == 0.0  # the rest of the way, at once
    assert channel.commands == 4  # the open, the half, the part and the rest: no command repeated


def test_a_partial_opening_that_would_not_let_go_is_held():
    rig = _rig()
    channel = GripperChannel(rig.gripper, LIMITS, CFG, may_open=lambda closure: closure >= 0.45)
    events = EventCoalescer(0.1)
    _feed(channel, rig, 0.0, 0.3)
    _feed(channel, rig, 0.5, 2.0)
    half = channel.closure_bound
    held = _feed(channel, rig, 0.0, 0.5, events)  # 0.45 is within LET_GO of the half-open bound
    assert (held[:, 0] == half).all() and rig.gripper.state().target == pytest.approx(0.5, abs=0.01)
    assert {e.kind for e in events.flush(10.0)} == {"gripper_open_held"}


def test_the_controller_hands_the_bound_to_its_filter():
    from sim.rotations import rotvec_to_matrix

    rig = _rig()
    loop = ControllerLoop(rig.arm, rig.gripper, SafetyFilter(LIMITS), CFG)
    s = rig.arm.state()
    p0, R = s.tcp_pose[:3].copy(), rotvec_to_matrix(s.tcp_pose[3:])
    from runtime.messages import ActionChunk

    seen = []
    for _ in range(10):  # 2 s of chunks holding the pose, the gripper half closed from the start
        times = (rig.now_ns() + 100_000_000 * np.arange(16)).astype(np.int64)
        acts = np.array([np.concatenate([p0, R[:, 0], R[:, 1], [0.5]]) for _ in times])
        assert loop.submit(ActionChunk(actions=acts, times_ns=times, obs_time_ns=int(times[0])))
        for _ in range(100):
            loop.cycle()
            rig.step(1)
            seen.append((loop.grip.closure_bound, loop.safety.workspace.closure, rig.world.gripper_position()))
    seen = np.array(seen)
    assert (seen[:, 0] == seen[:, 1]).all()  # the filter's points follow the channel every cycle
    assert (seen[:, 1] <= seen[:, 2] + 1e-9).all()
    assert seen[-1, 1] == pytest.approx(0.5, abs=0.05)


def test_the_gripper_is_asked_at_most_once_a_cycle():
    """The bound and the empty-close check share one state read (the real driver's is a socket round trip)."""
    rig = _rig()
    channel = GripperChannel(rig.gripper, LIMITS, ControllerConfig(gripper_levels=(0.0, 1.0)))
    asked = []
    state = rig.gripper.state

    def counted():
        asked.append(rig.now_ns())
        return state()

    rig.gripper.state = counted
    _feed(channel, rig, 0.0, 0.3)
    _feed(channel, rig, 1.0, 2.0)  # closes on nothing: both the bound and the empty-close check ask
    assert len(asked) >= 10 and len(asked) == len(set(asked))
    assert channel.empty_closes == 1 and channel.closure_bound == 0.0  # reopened: down again at once
