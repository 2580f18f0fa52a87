"""Density as the state: the void-ratio map (homogenization.material.density), its round trip and bounds."""

import math

import numpy as np
import pytest

from homogenization.material import density
from homogenization.material.density import DensityMap, default_map
from warp_hcell.core.errors import UserError


@pytest.mark.parametrize("dim", [2, 3])
def test_the_map_ends_at_the_densest_and_loosest_cells_and_round_trips(dim):
    m = default_map(dim, 0.55, 0.95)
    dense, loose = density.OPENING_RANGE_DEG[dim]
    assert m.alpha0_deg(0.55) == pytest.approx(dense, abs=1e-12)
    assert m.alpha0_deg(0.95) == pytest.approx(loose, abs=1e-12)
    assert m.alpha0_deg(0.75) == pytest.approx(0.5 * (dense + loose), abs=1e-12)  # linear in alpha0
    for e in np.linspace(0.55, 0.95, 9):
        assert m.void_ratio(m.alpha0_deg(e)) == pytest.approx(e, abs=1e-12)
    assert m.alpha0_deg(0.6) < m.alpha0_deg(0.9)  # denser: smaller opening


@pytest.mark.parametrize("e", [0.5, 1.0, -0.1, math.nan, math.inf])
def test_a_void_ratio_outside_the_map_is_one_line(e):
    with pytest.raises(UserError) as info:
        default_map(2, 0.55, 0.95).alpha0_deg(e)
    assert "\n" not in str(info.value)


def test_bad_maps_and_angles_are_refused():
    for args in ((0.9, 0.5, 40.0, 60.0), (-0.1, 0.5, 40.0, 60.0), (0.5, 0.9, 60.0, 40.0), (0.5, 0.9, 20.0, 60.0)):
        with pytest.raises(ValueError):
            DensityMap(*args)
    with pytest.raises(ValueError):
        default_map(2).void_ratio(35.0)
    assert DensityMap.from_dict(default_map(3).to_dict()) == default_map(3)


def test_the_array_rule_is_nan_outside_each_sets_range():
    alpha = density.opening_angle_deg(0.7, np.array([0.5, 0.75, 0.6]), np.array([0.9, 0.9, 0.6]), 40.0, 60.0)
    assert alpha[0] == pytest.approx(50.0) and np.isnan(alpha[1]) and np.isnan(alpha[2])


def test_current_void_ratio_and_the_default_e0_of_an_alpha0():
    # contraction (J < 1) lowers e: 1 + e is proportional to the volume
    assert density.current_void_ratio(0.8, [1.0, 0.9]) == pytest.approx([0.8, 0.62])
    m = default_map(2)
    assert density.initial_void_ratio(55.0, 2) == pytest.approx(m.void_ratio(55.0))
    assert math.isnan(density.initial_void_ratio(35.0, 2)) and math.isnan(density.initial_void_ratio(None, 3))
