"""The rest rule's pair test (``training.fast_increment.release_pair``) against the square-root test it replaces."""

import math

import numpy as np
import pytest

from training.fast_increment import release_pair, sqrt_bound


def test_sqrt_bound_is_the_largest_square_whose_root_is_within_reach():
    rng = np.random.default_rng(0)
    for reach in [*rng.uniform(0.5, 2.0, 2000), *10.0 ** rng.uniform(-6, 6, 2000), 1.0, 1.0 + 1e-9]:
        bound = sqrt_bound(reach)
        assert math.sqrt(bound) <= reach < math.sqrt(np.nextafter(bound, np.inf)), reach


@pytest.mark.parametrize("dim", [2, 3])
def test_release_pair_releases_where_the_square_root_test_does(dim):
    """Random cells, a third of them placed on the reach to the last bit (both sides), held grains at random."""
    rng = np.random.default_rng(dim)
    n, reach = 3000, 1.0 * (1.0 + 1e-9)
    x_i = rng.normal(size=(dim, n))
    direction = rng.normal(size=(dim, n))
    direction /= np.sqrt((direction ** 2).sum(axis=0))
    length = rng.uniform(0.9, 1.1, n)
    edge = rng.random(n) < 0.33
    length[edge] = reach * (1.0 + rng.integers(-3, 4, edge.sum()) * 1e-16)
    x_j = x_i + direction * length
    held_i, held_j = rng.random(n) < 0.5, rng.random(n) < 0.5
    expected_i, expected_j = held_i.copy(), held_j.copy()
    hits = np.zeros(n, dtype=bool)
    for c in range(n):
        if held_i[c] or held_j[c]:
            square = 0.0
            for a in range(dim):
                b = x_j[a, c] - x_i[a, c]
                square += b * b
            hits[c] = math.sqrt(square) <= reach
            if hits[c]:
                expected_i[c] = expected_j[c] = False
    released = release_pair(x_i, x_j, reach, held_i, held_j, np.empty(n))
    np.testing.assert_array_equal(held_i, expected_i)
    np.testing.assert_array_equal(held_j, expected_j)
    assert released == hits.any()
    held = edge & (expected_i | expected_j | hits)
    assert (held & hits).sum() > 10 and (held & ~hits).sum() > 10  # the last bit decides both ways
