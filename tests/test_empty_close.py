"""runtime/empty_close.py: fingers shut on nothing for a while are opened where they are, as the collector reopens."""

import numpy as np

from policy.stage import AIR, GRIPPER_COLUMN as G
from runtime.empty_close import HOLD_S, EmptyClose


def _chunk(grip) -> np.ndarray:
    a = np.zeros((len(grip), 10), np.float32)
    a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 7], a[:, G] = 0.3, 0.45, 0.05, 1.0, 1.0, grip
    return a


def test_a_hand_shut_on_nothing_is_opened_after_the_hold_and_its_poses_kept():
    e = EmptyClose()
    closed = _chunk(np.full(8, 1.0))
    assert e.chunk(closed, request=1.0, closure=0.99, t=10.0) is closed  # just shut: the policy's
    assert e.chunk(closed, 1.0, 0.99, 10.0 + HOLD_S / 2) is closed
    out = e.chunk(closed, 1.0, 0.99, 10.0 + HOLD_S)
    assert np.all(out[:, G] == 0.0) and e.opened == 1
    np.testing.assert_array_equal(out[:, :G], closed[:, :G])  # where the hand is: only the fingers change
    half = _chunk(np.array([1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 1.0, 1.0]))  # rows not asking closed stay as they are
    out = e.chunk(half, 1.0, 0.99, 10.0 + 2 * HOLD_S)
    np.testing.assert_array_equal(out[:, G], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0])


def test_a_hold_on_something_a_release_or_the_switch_off_leave_the_chunk_alone():
    closed = _chunk(np.full(8, 1.0))
    e = EmptyClose()
    for t in np.arange(0.0, 5.0, 0.1):  # a handle on the pads: 0.86-0.88 closed; a block 0.2-0.55
        assert e.chunk(closed, 1.0, 0.87, float(t)) is closed
    e.chunk(closed, 1.0, 0.99, 5.0)
    assert e.chunk(closed, 0.0, 0.99, 5.0 + HOLD_S) is closed and e.since is None  # asked open: not a close
    e.chunk(closed, 1.0, AIR, 7.0)
    assert e.chunk(closed, 1.0, AIR - 0.01, 7.0 + HOLD_S) is closed  # opened a little: no longer shut
    off = EmptyClose(enabled=False)
    off.chunk(closed, 1.0, 0.99, 0.0)
    assert off.chunk(closed, 1.0, 0.99, 3 * HOLD_S) is closed and off.opened == 0
