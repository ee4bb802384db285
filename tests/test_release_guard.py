"""The release guard (runtime/release_guard.py): an opening on the held object far from the object query's drop and
high above where the object lay is held back; an opening over the drop, a put-down on the table, an empty hand and
another grasp cycle are left to the policy."""

import numpy as np
import pytest

from runtime.release_guard import CARRY_M_S, FAR_M, LOW_M, NEAR_M, ReleaseGuard

OBJECT = np.array([-0.09, 0.52, 0.03])  # where the block lay (drawer_stow seed 100602)
DROP = np.array([0.185, 0.46, 0.16])   # the drop given to the policy
DT = 0.1  # s between a chunk's actions


class _Located:
    """An ObjectQuery stand-in: active, serving grasp cycle 0, the object at OBJECT, the drop at DROP."""

    active, stage = True, 0
    points = np.array([OBJECT, DROP + [0.0, 0.03, 0.0]])
    drop = DROP


def _chunk(xyz, opens_at=4, n=8):
    """(n, 10) actions holding still at `xyz`, the fingers asked open from action `opens_at` on."""
    out = np.zeros((n, 10), np.float32)
    out[:, :3] = xyz
    out[:, 3:9] = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0]
    out[:, 9] = 1.0
    out[opens_at:, 9] = 0.0
    return out


def test_an_opening_in_the_air_far_from_the_drop_is_held_closed():
    guard = ReleaseGuard()
    lifted = _chunk(OBJECT + [0.0, 0.0, 0.10])  # 100602: lifted 10 cm where it lay, 28 cm from the drop, let go
    out = guard.chunk(lifted, _Located(), 0, 1.0, 0.19, DT)
    np.testing.assert_array_equal(out[:, 9], 1.0)  # the fingers stay on the block
    assert guard.held == 1
    assert lifted[-1, 9] == 0.0  # the policy's chunk itself is not changed
    np.testing.assert_array_equal(out[:, 3:9], lifted[:, 3:9])  # the turn is the policy's


def test_a_held_chunk_is_carried_towards_the_drop_and_let_go_only_near_it():
    guard = ReleaseGuard()
    lifted = _chunk(OBJECT + [0.0, 0.0, 0.10])  # 100602: it hovered there asking to let go, every tick
    out = guard.chunk(lifted, _Located(), 0, 1.0, 0.19, DT)
    moved = out[:, :2] - lifted[:, :2]
    to_drop = (DROP[:2] - lifted[0, :2]) / np.linalg.norm(DROP[:2] - lifted[0, :2])
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), CARRY_M_S * DT * np.arange(1, 9), rtol=1e-5)
    np.testing.assert_allclose(moved / np.linalg.norm(moved, axis=1, keepdims=True), np.tile(to_drop, (8, 1)),
                               atol=1e-5)  # straight at the drop, no faster than CARRY_M_S
    np.testing.assert_allclose(out[:, 2], DROP[2], atol=1e-6)  # raised to the drop's height (it was at 13 cm)
    # once carried, an opening 5 cm from the drop (FAR_M would let it through) is held until NEAR_M
    near = _chunk(DROP + [0.05, 0.0, 0.0])
    out = guard.chunk(near, _Located(), 0, 1.0, 0.19, DT)
    np.testing.assert_array_equal(out[:, 9], 1.0)
    assert np.linalg.norm(out[-1, :2] - DROP[:2]) < 0.05 - 0.03  # and moved on towards it
    there = _chunk(DROP + [NEAR_M - 0.005, 0.0, 0.0])
    assert guard.chunk(there, _Located(), 0, 1.0, 0.19, DT) is there  # let go over the drop
    assert guard.held == 2


def test_only_the_openings_far_and_high_are_held():
    guard = ReleaseGuard()
    chunk = _chunk(OBJECT + [0.0, 0.0, 0.10], opens_at=2)
    chunk[6:, :3] = DROP + [FAR_M - 0.01, 0.0, 0.0]  # the last two actions over the drawer's edge
    out = guard.chunk(chunk, _Located(), 0, 1.0, 0.19, DT)
    np.testing.assert_array_equal(out[:, 9], [1.0] * 6 + [0.0] * 2)


@pytest.mark.parametrize("where, stage, command, closure", [
    (DROP + [0.03, -0.02, 0.0], 0, 1.0, 0.19),                    # over the drop: the let-go it is for
    (OBJECT + [0.02, 0.0, LOW_M - 0.01], 0, 1.0, 0.19),           # low: a put-down to take it again
    (OBJECT + [0.0, 0.0, 0.10], 0, 1.0, 0.95),                    # the fingers closed on nothing: an empty hand
    (OBJECT + [0.0, 0.0, 0.10], 0, 0.87, 0.79),                   # asked part-closed and there: nothing stops them
    (OBJECT + [0.0, 0.0, 0.10], 0, 0.0, 0.19),                    # already asked open
    (OBJECT + [0.0, 0.0, 0.10], 1, 1.0, 0.19),                    # another grasp cycle (the object query's is 0)
])
def test_other_openings_are_the_policys(where, stage, command, closure):
    guard = ReleaseGuard()
    chunk = _chunk(where)
    assert guard.chunk(chunk, _Located(), stage, command, closure, DT) is chunk
    assert guard.held == 0


def test_without_an_object_query_or_disabled_nothing_is_held():
    lifted = _chunk(OBJECT + [0.0, 0.0, 0.10])

    class _Inactive(_Located):
        active = False

    class _Unanswered(_Located):
        points, drop = None, None

    for objects in (_Inactive(), _Unanswered()):
        assert ReleaseGuard().chunk(lifted, objects, 0, 1.0, 0.19, DT) is lifted
    assert ReleaseGuard(enabled=False).chunk(lifted, _Located(), 0, 1.0, 0.19, DT) is lifted
