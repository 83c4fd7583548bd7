"""The exact Euclidean distance transform (mapping.distance) against scipy's."""

import numpy as np
import pytest
from scipy import ndimage

from mapping.distance import no_target, squared_distances


@pytest.mark.parametrize("density", [0.001, 0.02, 0.3, 0.9])
def test_squared_distances_equal_scipys_transform(density):
    rng = np.random.default_rng(11)
    for _ in range(30):
        targets = rng.random(tuple(rng.integers(1, 90, 2))) < density
        if not targets.any():
            continue
        d2 = squared_distances(targets)
        assert d2.dtype == np.int64 and d2.shape == targets.shape
        assert (d2[targets] == 0).all() and (d2[~targets] > 0).all()
        # the square root in float64 is scipy's result to the bit
        np.testing.assert_array_equal(np.sqrt(d2), ndimage.distance_transform_edt(~targets))


def test_a_grid_without_targets_is_no_target_everywhere():
    d2 = squared_distances(np.zeros((7, 5), bool))
    assert (d2 == no_target((7, 5))).all() and no_target((7, 5)) > 6**2 + 4**2


def test_distances_along_a_lone_target_row_and_column():
    targets = np.zeros((5, 8), bool)
    targets[2, 3] = True
    d2 = squared_distances(targets)
    ii, jj = np.mgrid[0:5, 0:8]
    np.testing.assert_array_equal(d2, (ii - 2) ** 2 + (jj - 3) ** 2)


@pytest.mark.parametrize("cap", [1, 3, 19, 40])
def test_capped_distances_are_exact_below_the_cap(cap):
    """Below cap² the capped transform is the exact one; from it on, cap²."""
    from mapping.distance import capped_squared_distances

    rng = np.random.default_rng(cap)
    for density in (0.001, 0.02, 0.3):
        targets = rng.random((rng.integers(20, 120), rng.integers(20, 120))) < density
        exact = squared_distances(targets)
        got = capped_squared_distances(targets, cap)
        np.testing.assert_array_equal(got, np.minimum(exact, cap * cap))
