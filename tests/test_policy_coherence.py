"""Backward coherence (policy/coherence.py): of several chunks for one observation, the one that goes on from the
chunk before runs."""

import numpy as np
import pytest

from policy.coherence import Coherence, check_samples, chunk_distance

DT = 0.1


def _line(x0: float, dx: float, grip: float = 0.0, n: int = 8) -> np.ndarray:
    """A chunk moving along x from x0 by dx per row, rotation identity, constant gripper request."""
    a = np.zeros((n, 10), np.float32)
    a[:, 0] = x0 + dx * (1 + np.arange(n))
    a[:, 3], a[:, 7], a[:, 9] = 1.0, 1.0, grip
    return a


def test_distance_compares_the_rows_that_fall_at_the_same_times():
    earlier = _line(0.0, 0.01)
    same_path = _line(0.01, 0.01)  # made one tick later on the same line: rows 0..6 are earlier's 1..7
    assert chunk_distance(same_path[None], earlier, 1)[0] == pytest.approx(0.0, abs=1e-5)
    assert chunk_distance(same_path[None], earlier, 0)[0] > 1.0  # misaligned: one row (1 cm) off on every row
    assert chunk_distance(same_path[None], earlier, 8)[0] == 0.0  # nothing in common


def test_the_gripper_and_the_near_rows_weigh():
    earlier = _line(0.0, 0.01, grip=1.0)
    opens = _line(0.01, 0.01, grip=0.0)
    lags = _line(0.005, 0.01, grip=1.0)  # 5 mm behind on every row, still closed
    d = chunk_distance(np.stack([opens, lags]), earlier, 1)
    assert d[1] < d[0]  # letting go where the chunk before held is a bigger change than 5 mm
    near = _line(0.01, 0.01)
    far = near.copy()
    near[0, 0] += 0.02
    far[-1, 0] += 0.02
    d = chunk_distance(np.stack([near, far]), _line(0.0, 0.01), 1)
    assert d[0] > d[1]  # the same 2 cm counts more in the next row than six rows on


def test_pick_keeps_to_the_mode_it_is_in():
    c = Coherence(samples=3)
    first = np.stack([_line(0.0, 0.01), _line(0.0, -0.01), _line(0.0, 0.0)])
    np.testing.assert_array_equal(c.pick(first, 0.0, DT), first[0])  # nothing before: the first sample
    assert c.chose == 0
    later = np.stack([_line(0.0, -0.01), _line(0.0, 0.0), _line(0.01, 0.01)])  # the third goes on along +x
    np.testing.assert_array_equal(c.pick(later, DT, DT), later[2])
    assert (c.chose, c.changed) == (1, 1)
    c.forget()  # the arm moved otherwise: no earlier chunk to keep to
    np.testing.assert_array_equal(c.pick(later, 2 * DT, DT), later[0])
    gap = np.stack([_line(0.0, 0.0), _line(0.0, 0.01)])
    np.testing.assert_array_equal(c.pick(gap, 20 * DT, DT), gap[0])  # the last chunk ran out long ago
    assert c.chose == 1


def test_one_sample_is_the_plain_sampler_and_bad_counts_are_refused():
    c = Coherence()
    a = _line(0.0, 0.01)[None]
    np.testing.assert_array_equal(c.pick(a, 0.0, DT), a[0])
    np.testing.assert_array_equal(c.pick(a, DT, DT), a[0])
    assert c.chose == 0
    for bad in (0, 33, 2.0, True):
        with pytest.raises(ValueError, match="coherence samples"):
            check_samples(bad)
