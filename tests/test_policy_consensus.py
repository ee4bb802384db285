"""Several sampler draws, one chunk (policy/consensus.py): the medoid keeps a draw from the crowd, never an
outlier or an average of two modes."""

from __future__ import annotations

import numpy as np
import pytest

from policy.consensus import MAX_DRAWS, check_draws, medoid


def test_the_medoid_is_the_draw_nearest_the_others_not_an_outlier():
    rng = np.random.default_rng(0)
    crowd = 0.01 * rng.standard_normal((6, 8, 10))
    crowd[3] = 0.0  # the crowd's centre
    outlier = np.full((1, 8, 10), 2.0)
    chunks = np.concatenate([outlier, crowd])
    assert medoid(chunks) == 4


def test_of_two_modes_the_medoid_is_a_draw_of_the_larger():
    # three draws go left, two right: a mean would go straight, where no draw went
    left, right = np.full((3, 8, 2), -1.0), np.full((2, 8, 2), 1.0)
    left += np.arange(3)[:, None, None] * 0.01
    chunks = np.concatenate([right, left])
    k = medoid(chunks)
    assert k >= 2 and np.all(chunks[k] < 0)


def test_one_or_two_draws_keep_the_first():
    assert medoid(np.ones((1, 4, 3))) == 0 and medoid(np.stack([np.zeros((4, 3)), np.ones((4, 3))])) == 0


@pytest.mark.parametrize("bad", [0, -1, MAX_DRAWS + 1, 2.5, True, "3", None])
def test_a_draw_count_outside_its_range_is_refused_with_the_range(bad):
    with pytest.raises(ValueError, match=rf"expected an integer in \[1, {MAX_DRAWS}\]"):
        check_draws(bad)


def test_a_draw_count_in_range_is_kept():
    assert check_draws(1) == 1 and check_draws(np.int64(5)) == 5
