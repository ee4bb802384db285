"""The grasp steer (runtime/grasp_steer.py): after a close on nothing, a retry's approach is moved over the object
the object query located; a first grasp, a slip and a chunk headed elsewhere are left to the policy."""

import numpy as np
import pytest

from runtime.grasp_steer import EASE_S, GraspSteer

OBJECT = np.array([0.10, 0.30, 0.03])
DT = 0.1


class _Located:
    """An ObjectQuery stand-in: active, serving grasp cycle 0, the object at OBJECT."""

    active, stage = True, 0
    points = np.array([OBJECT, [-0.2, 0.45, 0.04]])


def _chunk(end_xy, end_z=0.05, n=8):
    """(n, 10) actions from 10 cm above the object down to (end_xy, end_z), an upright rot6d, the fingers open."""
    out = np.zeros((n, 10), np.float32)
    start = np.array([*OBJECT[:2], OBJECT[2] + 0.10])
    for k in range(n):
        out[k, :3] = start + (k + 1) / n * (np.array([*end_xy, end_z]) - start)
    out[:, 3:9] = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0]
    return out


def _missed(steer, t0=0.0):
    """A close whose fingers shut on nothing: closure 0.3, 0.7, 0.98 in the first 0.3 s, then the reopen."""
    for k, closure in enumerate((0.3, 0.7, 0.98)):
        steer.update(1.0, closure, 0, t0 + DT * k)
    steer.update(0.0, 0.6, 0, t0 + 0.3)


def test_a_retry_after_a_close_on_nothing_ends_over_the_located_object():
    steer = GraspSteer()
    off = OBJECT[:2] + [0.0, 0.06]  # the policy's aim: 6 cm beyond the object, as drawer_stow 100600
    chunk = _chunk(off)
    assert steer.chunk(chunk, _Located(), 0, 0.0, DT) is chunk  # a first grasp: the policy's own
    _missed(steer)
    assert steer.misses == 1
    moved = steer.chunk(chunk, _Located(), 0, 0.0, DT)
    np.testing.assert_allclose(moved[-1, :2], OBJECT[:2], atol=1e-6)  # ends over the object
    np.testing.assert_allclose(moved[0, :2] - chunk[0, :2], [0.0, -0.06 * DT / EASE_S], atol=1e-6)  # eased in
    np.testing.assert_array_equal(moved[:, 2:], chunk[:, 2:])  # heights, turn and fingers the policy's
    assert steer.steered == 1


@pytest.mark.parametrize("end_xy, end_z", [((0.10, 0.30 + 0.12), 0.05),   # headed 12 cm away: something else
                                            ((0.10, 0.30 + 0.01), 0.05),   # within 1.5 cm: the policy's aim stands
                                            ((0.10, 0.30 + 0.05), 0.15)])  # still 12 cm up: not going for it yet
def test_a_chunk_headed_elsewhere_close_by_or_high_is_left_alone(end_xy, end_z):
    steer = GraspSteer()
    _missed(steer)
    chunk = _chunk(end_xy, end_z)
    assert steer.chunk(chunk, _Located(), 0, 0.0, DT) is chunk


def test_only_the_object_querys_cycle_with_open_fingers_and_the_steer_on_is_steered():
    chunk = _chunk(OBJECT[:2] + [0.0, 0.05])
    steer = GraspSteer()
    _missed(steer)
    assert steer.chunk(chunk, _Located(), 0, 1.0, DT) is chunk  # the fingers commanded shut: no move under them
    assert steer.chunk(chunk, _Located(), 1, 0.0, DT) is chunk  # another grasp cycle than the query's
    off = GraspSteer(enabled=False)
    _missed(off)
    assert off.chunk(chunk, _Located(), 0, 0.0, DT) is chunk
    steer.update(0.0, 0.0, 1, 5.0)  # a grasp cycle ended: its misses are forgotten
    steer.update(0.0, 0.0, 0, 5.1)
    assert steer.misses == 0 and steer.chunk(chunk, _Located(), 0, 0.0, DT) is chunk


def test_a_slip_from_fingers_that_held_is_no_miss_and_each_close_counts_once():
    steer = GraspSteer()
    for k in range(30):  # held an object 3 s (closure 0.55), then it slipped out and the fingers shut
        steer.update(1.0, 0.55 if k < 25 else 0.99, 0, DT * k)
    assert steer.misses == 0
    steer.update(0.0, 0.5, 0, 3.1)
    for k in range(5):  # a close on nothing, shut for 0.5 s before the reopen: one miss
        steer.update(1.0, 0.99, 0, 4.0 + DT * k)
    assert steer.misses == 1
