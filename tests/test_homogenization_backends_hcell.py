"""Closed-form H-cell geometry and Love-Weber moment (spec sections 2, 3, 7)."""

import numpy as np
import pytest

from warp_hcell.mesostructures import hcell

D = 1.0
RNG = np.random.default_rng(20260101)


def _random_branches(n=50):
    d1 = RNG.uniform(0.9, 1.0, n)
    d2 = RNG.uniform(0.9, 1.0, n)
    alpha = np.radians(RNG.uniform(30.0, 89.0, n))
    return d1, d2, alpha


def _spec_positions(d1, d2, alpha):
    """Grain centres written from the table of spec section 2, as (x_n, x_t)."""
    a, b = d1 * np.sin(alpha), d1 * np.cos(alpha)
    z = np.zeros_like(d1)
    x_t = np.stack([z, -a, -a, z, a, a], axis=-1)
    x_n = np.stack([d2 / 2 + b, d2 / 2, -d2 / 2, -d2 / 2 - b, -d2 / 2, d2 / 2], axis=-1)
    return np.stack([x_n, x_t], axis=-1)


def _shoelace(points):
    """Area of the polygon through points (n_cells, n, 2), any orientation."""
    x, y = points[..., 0], points[..., 1]
    return 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1))


def test_regular_hexagon_at_60_degrees():
    alpha = np.radians([60.0])
    l1, l2 = hcell.lengths(np.array([D]), np.array([D]), alpha)
    np.testing.assert_allclose(l1, 2.0 * D, rtol=1e-15)
    np.testing.assert_allclose(l2, np.sqrt(3.0) * D, rtol=1e-15)
    pos = hcell.grain_positions(l1, l2, np.array([D / 2]))[0]
    ring = pos[[0, 1, 2, 3, 4, 5]]
    sides = np.linalg.norm(ring - np.roll(ring, -1, axis=0), axis=1)
    np.testing.assert_allclose(sides, D, rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(pos, axis=1), D, rtol=1e-14)  # all on the circumcircle
    area = hcell.cell_area(l1, l2, np.array([D]))
    np.testing.assert_allclose(area, 1.5 * np.sqrt(3.0) * D**2, rtol=1e-14)


def test_positions_follow_the_spec_table_and_the_length_definitions():
    d1, d2, alpha = _random_branches()
    l1, l2 = hcell.lengths(d1, d2, alpha)
    pos = hcell.grain_positions(l1, l2, d2 / 2)
    np.testing.assert_allclose(pos, _spec_positions(d1, d2, alpha), atol=1e-14)
    np.testing.assert_allclose(pos[:, 0, 0] - pos[:, 3, 0], l1, rtol=1e-14)  # centre 1 to centre 4
    np.testing.assert_allclose(pos[:, 5, 1] - pos[:, 1, 1], l2, rtol=1e-14)  # between the columns


def test_branches_round_trip_from_alpha():
    d1, d2, alpha = _random_branches()
    l1, l2 = hcell.lengths(d1, d2, alpha)
    s1, s2 = hcell.branches_from_alpha(l1, l2, alpha)
    np.testing.assert_allclose(np.stack([s1, s2]), np.stack([d1, d2]), rtol=1e-13)


def test_cell_area_is_the_hexagon_through_the_centres():
    d1, d2, alpha = _random_branches()
    l1, l2 = hcell.lengths(d1, d2, alpha)
    area = hcell.cell_area(l1, l2, d2)
    np.testing.assert_allclose(area, _shoelace(_spec_positions(d1, d2, alpha)), rtol=1e-13)
    np.testing.assert_allclose(area, l2 * (l1 - d1 * np.cos(alpha)), rtol=1e-13)


def _love_weber_by_contacts(d1, d2, alpha, N1, N2, T1, kn):
    """Sum of f (x) l over the contacts: force on grain j from grain i, branch i -> j.

    Contact 1-2 follows spec section 4 (force N1 n12 - T1 t12); 1-6, 4-3 and 4-5 are its
    mirror images in t, n and both. Type-2 and extra contacts are built from the centres.
    """
    pos = _spec_positions(d1, d2, alpha)  # (n_cells, 6, 2), (x_n, x_t)
    c, s = np.cos(alpha), np.sin(alpha)
    n12 = np.stack([-c, -s], axis=1)  # spec: (-sin a, -cos a) in (t, n) order
    t12 = np.stack([s, -c], axis=1)  # spec: (-cos a, sin a) in (t, n) order
    branch12 = pos[:, 1] - pos[:, 0]
    np.testing.assert_allclose(branch12, d1[:, None] * n12, atol=1e-14)
    force12 = N1[:, None] * n12 - T1[:, None] * t12
    moment = np.zeros((d1.size, 2, 2))
    for mirror in ([1, 1], [1, -1], [-1, 1], [-1, -1]):  # 1-2, 1-6, 4-3, 4-5
        m = np.array(mirror, dtype=float)
        moment += (m * force12)[:, :, None] * (m * branch12)[:, None, :]
    pairs = [(1, 2, N2), (5, 4, N2)]  # type 2
    for i, j in [(0, 3), (1, 5), (2, 4)]:  # extra contacts, linear law without tension
        length = np.linalg.norm(pos[:, j] - pos[:, i], axis=1)
        pairs.append((i, j, kn * np.maximum(D - length, 0.0)))
    for i, j, normal in pairs:
        branch = pos[:, j] - pos[:, i]
        unit = branch / np.linalg.norm(branch, axis=1)[:, None]
        moment += (normal[:, None] * unit)[:, :, None] * branch[:, None, :]
    return moment


@pytest.mark.parametrize("extra", [False, True])
def test_moment_equals_the_sum_over_contacts(extra):
    kn = 2e8
    if extra:  # grains 2-6 and 3-5 touch (l2 < D) in half the cells, 1-4 (l1 < D) in the others
        d1 = np.array([0.99, 0.95, 0.9, 0.9])
        d2 = np.array([0.98, 0.99, 0.02, 0.05])
        alpha = np.radians([30.0, 31.0, 89.0, 88.0])
    else:
        d1, d2, alpha = _random_branches(20)
    n = d1.size
    N1, N2 = RNG.uniform(0, 1e6, n), RNG.uniform(0, 1e6, n)
    T1 = RNG.uniform(-0.5, 0.5, n) * N1
    l1, l2 = hcell.lengths(d1, d2, alpha)
    if extra:
        assert np.any(l1 < D) and np.any(l2 < D)
    moment, area = hcell.love_weber_moment(alpha, N1, N2, T1, l1, l2, kn=kn, diameter=D)
    assert moment.shape == (n, 2, 2) and area.shape == (n,)
    np.testing.assert_allclose(moment, _love_weber_by_contacts(d1, d2, alpha, N1, N2, T1, kn), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(area, hcell.cell_area(l1, l2, d2), rtol=1e-13)


def test_moment_formulas_of_section_7_and_compression_positive():
    d1, d2, _ = _random_branches(20)
    alpha = np.radians(RNG.uniform(40.0, 80.0, 20))  # l1, l2 > D: no extra contacts
    N1, N2, T1 = RNG.uniform(0, 1e6, (3, 20))
    T1 = T1 - 5e5
    l1, l2 = hcell.lengths(d1, d2, alpha)
    moment, _ = hcell.love_weber_moment(alpha, N1, N2, T1, l1, l2, kn=2e8, diameter=D)
    c, s = np.cos(alpha), np.sin(alpha)
    S_nn = 4 * N1 * d1 * c**2 + 4 * T1 * d1 * s * c + 2 * N2 * d2
    S_tt = 4 * N1 * d1 * s**2 - 4 * T1 * d1 * s * c
    np.testing.assert_allclose(moment[:, 0, 0], S_nn, rtol=1e-12)
    np.testing.assert_allclose(moment[:, 1, 1], S_tt, rtol=1e-12, atol=1e-6)
    assert np.all(moment[:, 0, 1] == 0.0) and np.all(moment[:, 1, 0] == 0.0)
    pure_normal, _ = hcell.love_weber_moment(alpha, N1, N2, 0 * T1, l1, l2, kn=2e8, diameter=D)
    assert np.all(pure_normal[:, 0, 0] > 0) and np.all(pure_normal[:, 1, 1] > 0)
