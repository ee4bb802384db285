"""The release guard (runtime/release_guard.py): an opening on the held object far from the object query's drop and
high above where the object lay is held back; an opening over the drop, a put-down on the table, an empty hand and
another grasp cycle are left to the policy."""

import numpy as np
import pytest

from runtime.release_guard import FAR_M, LOW_M, ReleaseGuard

OBJECT = np.array([-0.09, 0.52, 0.03])  # where the block lay (drawer_stow seed 100602)
DROP = np.array([0.185, 0.46, 0.16])   # the drop given to the policy


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
    out = guard.chunk(lifted, _Located(), 0, 1.0, 0.19)
    np.testing.assert_array_equal(out[:, 9], 1.0)  # the fingers stay on the block
    np.testing.assert_array_equal(out[:, :9], lifted[:, :9])  # the motion is the policy's
    assert guard.held == 1
    assert lifted[-1, 9] == 0.0  # the policy's chunk itself is not changed


def test_only_the_openings_far_and_high_are_held():
    guard = ReleaseGuard()
    chunk = _chunk(OBJECT + [0.0, 0.0, 0.10], opens_at=2)
    chunk[6:, :3] = DROP + [FAR_M - 0.01, 0.0, 0.0]  # the last two actions over the drawer's edge
    out = guard.chunk(chunk, _Located(), 0, 1.0, 0.19)
    np.testing.assert_array_equal(out[:, 9], [1.0] * 6 + [0.0] * 2)


@pytest.mark.parametrize("where, stage, command, closure", [
    (DROP + [0.03, -0.02, 0.0], 0, 1.0, 0.19),                    # over the drop: the let-go it is for
    (OBJECT + [0.02, 0.0, LOW_M - 0.01], 0, 1.0, 0.19),           # low: a put-down to take it again
    (OBJECT + [0.0, 0.0, 0.10], 0, 1.0, 0.95),                    # the fingers closed on nothing: an empty hand
    (OBJECT + [0.0, 0.0, 0.10], 0, 0.0, 0.19),                    # already asked open
    (OBJECT + [0.0, 0.0, 0.10], 1, 1.0, 0.19),                    # another grasp cycle (the object query's is 0)
])
def test_other_openings_are_the_policys(where, stage, command, closure):
    guard = ReleaseGuard()
    chunk = _chunk(where)
    assert guard.chunk(chunk, _Located(), stage, command, closure) is chunk
    assert guard.held == 0


def test_without_an_object_query_or_disabled_nothing_is_held():
    lifted = _chunk(OBJECT + [0.0, 0.0, 0.10])

    class _Inactive(_Located):
        active = False

    class _Unanswered(_Located):
        points, drop = None, None

    for objects in (_Inactive(), _Unanswered()):
        assert ReleaseGuard().chunk(lifted, objects, 0, 1.0, 0.19) is lifted
    assert ReleaseGuard(enabled=False).chunk(lifted, _Located(), 0, 1.0, 0.19) is lifted
