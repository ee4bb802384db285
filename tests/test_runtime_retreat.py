"""runtime.retreat: before a skill whose data starts at home, the arm goes back there, up first, then across."""

import numpy as np

from policy.action_frame import rot6d_of, rotations
from policy.pace import Pace
from runtime.phases import Sequencer, phases_for
from runtime.retreat import Retreat, angle_between, arrived, free_fingers, retreat_chunk


def _pose(p, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    down = np.array([[c, -s, 0.0], [-s, -c, 0.0], [0.0, 0.0, -1.0]])  # fingers down, turned by yaw
    return np.concatenate([p, rot6d_of(down)])


HOME = _pose([0.0, 0.45, 0.40], 0.0)
IN_DRAWER = _pose([0.20, 0.60, 0.18], 0.9)


def test_the_retreat_lifts_straight_up_then_goes_across_to_the_start_turning_on_the_way():
    cfg = Retreat(speed=0.1, turn=0.5)
    chunk = retreat_chunk(IN_DRAWER, HOME, 0.3, 8, 0.1, cfg)
    assert chunk.shape == (8, 10) and np.all(chunk[:, 9] == np.float32(0.3))  # the gripper held as it is
    np.testing.assert_allclose(chunk[:, :2], np.tile(IN_DRAWER[:2], (8, 1)), atol=1e-6)  # up first: 22 cm to go
    np.testing.assert_allclose(np.diff(chunk[:, 2]), 0.01, atol=1e-6)  # 0.1 m/s x 0.1 s an action
    R = rotations(chunk[:, 3:9])
    turned = [angle_between(rotations(IN_DRAWER[3:9]), r) for r in R]
    np.testing.assert_allclose(turned, 0.05 * np.arange(1, 9), atol=1e-5)  # 0.5 rad/s about one axis
    assert all(abs(np.linalg.det(r) - 1.0) < 1e-5 for r in R)
    far = retreat_chunk(IN_DRAWER, HOME, 0.0, 80, 0.1, cfg)  # 8 s of it: up 22 cm, across 25 cm, then there
    up = far[:22]
    assert np.all(np.abs(up[:, :2] - IN_DRAWER[:2]) < 1e-6) and abs(far[21, 2] - HOME[2]) < 1e-6
    np.testing.assert_allclose(far[30, 2], HOME[2], atol=1e-6)  # across at the start's height
    np.testing.assert_allclose(far[-1, :9], HOME, atol=1e-5)
    assert arrived(far[-1, :9], HOME) and not arrived(far[30, :9], HOME)


def test_a_start_below_the_arm_is_reached_straight_and_a_half_turn_is_turned():
    low = _pose([0.0, 0.45, 0.10], np.pi)
    chunk = retreat_chunk(HOME, low, 0.0, 40, 0.1, Retreat(speed=0.1, turn=1.0))
    np.testing.assert_allclose(chunk[:, :2], np.tile(HOME[:2], (40, 1)), atol=1e-6)  # no lift above the arm
    np.testing.assert_allclose(chunk[-1, :9], low, atol=1e-5)
    half = [angle_between(rotations(HOME[3:9]), rotations(a[3:9])) for a in chunk[:5]]
    np.testing.assert_allclose(half, 0.1 * np.arange(1, 6), atol=1e-5)


STOW = ("drawer_stow",)  # a bundle taught the family whose skill drawer_put's middle phase is
AT_HANDLE = _pose([0.20, 0.50, 0.13], 0.9)  # where opening the drawer leaves the arm


def test_the_sequencer_retreats_once_the_drawer_is_open_and_hands_over_at_the_start_or_when_its_time_is_up():
    seq = Sequencer(phases_for("drawer_put", Pace({}), tasks=STOW), lambda t: t, "cmd",
                    retreat=Retreat(speed=0.1, max_seconds=1.0, settle=0.0))
    seq.update(0, HOME)
    assert seq.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) is None  # opening the drawer: the policy's
    assert seq.update(1, AT_HANDLE) and seq.describe("cmd").endswith("from the start pose")
    chunks = [seq.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) for _ in range(12)]
    assert all(c is not None for c in chunks[:10]) and chunks[10] is None and chunks[11] is None
    assert seq.retreat_seconds == [1.0]  # held where it was: handed over at max_seconds
    seq.update(2, AT_HANDLE)  # let go in the drawer: "close the drawer" goes on from there, as its data does
    assert seq.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) is None and seq.retreat_seconds == [1.0]
    again = Sequencer(phases_for("drawer_put", Pace({}), tasks=STOW), lambda t: t, "cmd", retreat=Retreat(settle=0.0))
    again.update(0, HOME), again.update(1, AT_HANDLE)
    assert again.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) is not None and again.retreat_seconds == [0.1]
    assert again.retreat(HOME, 0.0, 0.0, 8, 0.1) is None and again.retreat_seconds == [0.1]  # there: the skill's turn
    plain = Sequencer(phases_for("drawer_put", Pace({})), lambda t: t, "cmd")  # a bundle without the skill
    plain.update(0, HOME), plain.update(1, AT_HANDLE)
    assert plain.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) is None and plain.retreat_seconds == []


def test_the_retreat_waits_for_an_empty_hand_and_leaves_a_held_handle_to_the_skill():
    # a handle the half-open pre-shape still touches: request 0.5, the fingers stopped at 0.40 on it
    assert not free_fingers(0.5, 0.40) and free_fingers(0.5, 0.49)
    assert not free_fingers(0.0, 0.40) and free_fingers(0.0, 0.01)  # told to open: free once they have
    cfg = Retreat(wait_seconds=1.0, settle=0.4)
    held = Sequencer(phases_for("drawer_put", Pace({}), tasks=STOW), lambda t: t, "cmd", retreat=cfg)
    held.update(0, HOME), held.update(1, AT_HANDLE)
    waits = [held.retreat(AT_HANDLE, 0.5, 0.40, 8, 0.1) for _ in range(10)]
    for chunk in waits[:9]:  # while it waits the arm holds still, the hand told to open
        assert chunk.shape == (8, 10) and np.allclose(chunk[:, :9], AT_HANDLE[:9]) and np.all(chunk[:, 9] == 0.0)
    assert waits[9] is None  # waited 1 s, still held: the skill goes on from here
    assert held.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1) is None and held.retreat_seconds == []  # not later either
    freed = Sequencer(phases_for("drawer_put", Pace({}), tasks=STOW), lambda t: t, "cmd", retreat=cfg)
    freed.update(0, HOME), freed.update(1, AT_HANDLE)
    opening = [(0.5, 0.40), (0.0, 0.30), (0.0, 0.02), (0.0, 0.0), (0.0, 0.0)]  # free from the third tick
    holds = [freed.retreat(AT_HANDLE, c, x, 8, 0.1) for c, x in opening]
    assert all(np.allclose(h[:, :3], AT_HANDLE[:3]) and np.all(h[:, 9] == 0.0) for h in holds)
    assert freed.retreat_seconds == []  # holding is not retreating
    chunk = freed.retreat(AT_HANDLE, 0.0, 0.0, 8, 0.1)  # 0.4 s free: back to the start
    assert chunk is not None and np.all(chunk[:, 9] == 0.0) and freed.retreat_seconds == [0.1]
