"""The release point moved by the held block's offset from the TCP (policy/hand_offset.py, through the goal
query): taken across the pads when the fingers come to rest on something, turned with the TCP, dropped when
they open."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from policy.action_frame import rot6d_of
from policy.goal_query import GoalQuery, goal_query_spec
from policy.hand_offset import HandOffset
from policy.testing import STACK, StillBundle

DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # TCP z down, fingers close along x


def _yawed(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ DOWN


def _proprio(tcp, closure, before=None, yaw_deg=0.0) -> np.ndarray:
    """(2, 16) proprio: TCP position and rot6d, closure now and `before` (default the same) one step earlier."""
    rows = []
    for c in (closure if before is None else before, closure):
        rows.append(np.concatenate([tcp, rot6d_of(_yawed(yaw_deg)), [c], np.zeros(6)]))
    return np.array(rows)


def test_the_offset_across_the_pads_is_taken_when_the_fingers_rest_on_the_block():
    h = HandOffset()
    tcp, block = np.array([0.3, 0.4, 0.1]), np.array([0.31, 0.385, 0.02])  # 1 cm along x, 1.5 cm along -y
    h.update(_proprio(tcp, 0.0), block)
    h.update(_proprio(tcp, 0.45, before=0.3), block)  # still closing: nothing taken yet
    assert h.across_m is None
    h.update(_proprio(tcp, 0.45), block)  # at rest on it: the TCP's y axis is the base's -y here
    assert h.across_m == pytest.approx(0.015) and h.taken == [0.015]  # x, the closing axis, is centred


def test_the_release_point_moves_by_the_offset_turned_with_the_tcp_and_not_once_let_go():
    h = HandOffset()
    tcp = np.array([0.3, 0.4, 0.1])
    h.update(_proprio(tcp, 0.45), tcp + [0.0, -0.02, 0.0])  # 2 cm along the TCP's y axis (base -y)
    goal = np.array([0.1, 0.5, 0.08], np.float32)
    moved = h.shift(goal, _proprio(tcp, 0.45))
    np.testing.assert_allclose(moved, [0.1, 0.52, 0.08], atol=1e-6)  # the TCP goes 2 cm the other way
    assert moved.dtype == np.float32
    turned = h.shift(goal, _proprio(tcp, 0.45, yaw_deg=90.0))  # the gripper turned a quarter: y now base +x
    np.testing.assert_allclose(turned, [0.08, 0.5, 0.08], atol=1e-6)
    h.update(_proprio(tcp, 0.05), None)  # the fingers open: the block is gone
    np.testing.assert_array_equal(h.shift(goal, _proprio(tcp, 0.0)), goal)
    h.update(_proprio(tcp, 0.45), tcp + [0.0, -0.01, 0.0])  # a re-grasp: the block has moved since the look
    assert h.across_m is None and h.taken == [pytest.approx(0.02)]


@pytest.mark.parametrize("closure, block", [(0.99, [0.3, 0.38, 0.02]),  # closed on nothing
                                            (0.45, [0.3, 0.34, 0.02]),  # 6 cm across: not the block held
                                            (0.45, None)])  # no point found
def test_no_offset_from_an_empty_close_a_far_point_or_none(closure, block):
    h = HandOffset()
    h.update(_proprio(np.array([0.3, 0.4, 0.1]), closure), None if block is None else np.array(block))
    assert h.across_m is None and h.taken == []


def test_the_goal_query_asks_for_the_block_to_pick_up_too_and_shifts_its_release():
    b = StillBundle(families=("stack",), look=(0.15, 0.08, 0.1))
    b.goal_query = replace(b.goal_query, hand_offset=True)
    q = GoalQuery(b, STACK, "stack")
    p = _proprio(np.array([0.1, 0.45, 0.1]), 0.0)
    for _ in range(3):
        q.ask({}, p)
    assert len(b.asked) == 6 and q.settled  # each look asks the swapped command and the command as given
    swapped = {tuple(e) for e in b.asked[0::2]}
    as_given = {tuple(e) for e in b.asked[1::2]}
    assert swapped == {tuple(b.embed(q.swapped))} and as_given == {tuple(b.embed(STACK))}
    np.testing.assert_allclose(q.object_point, [0.1, 0.44, 0.02])  # the median of 0.42, 0.44, 0.46
    unmoved = q.release({}, p)
    held = q.release({}, _proprio(np.array([0.1, 0.45, 0.1]), 0.5))  # 1 cm along base -y = the TCP's +y
    np.testing.assert_allclose(held[:3] - unmoved[:3], [0.0, 0.01, 0.0], atol=1e-6)


def test_hand_offset_needs_a_look_and_a_boolean():
    m = {"tasks": ["stack"], "release_input": True,
         "goal_query": {"families": ["stack"], "offset_m": [0, 0, 0], "ticks": 3, "locator": True,
                        "look_m": [0.15, 0.08, 0.1], "hand_offset": True}}
    assert goal_query_spec(m).hand_offset
    with pytest.raises(ValueError, match="hand_offset 'yes': expected true or false"):
        goal_query_spec({**m, "goal_query": {**m["goal_query"], "hand_offset": "yes"}})
    no_look = {k: v for k, v in m["goal_query"].items() if k != "look_m"}
    with pytest.raises(ValueError, match="hand_offset needs look_m"):
        goal_query_spec({**m, "goal_query": no_look})
