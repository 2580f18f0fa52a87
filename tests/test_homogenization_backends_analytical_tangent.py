"""Consistent tangent of the analytical H-cell against central differences of its step."""

import numpy as np
import pytest

from homogenization.backends.analytical import AnalyticalCell
from tangent_fd import relative_error
from warp_hcell.core.checks import central_difference_tangent
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import ContactLaw

LAW = ContactLaw()
R = 0.5


@pytest.fixture(scope="module")
def model():
    return AnalyticalCell(LAW, R)


@pytest.fixture(scope="module")
def sheared(model):
    """Cells of alpha0 35-70 deg, isotropically compressed then sheared at constant volume
    in five local directions: a mix of sticking, sliding and open type-1 contacts."""
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 5)
    c2 = np.tile(np.cos(2 * np.linspace(0, np.pi / 2, 5)), 4)
    state = model.init_state([h_cell(a, R) for a in alpha0], alpha0.size)
    for _ in range(200):
        state, _ = model.step(state, np.full((alpha0.size, 2), 5e-6))
    d_eps = np.stack([1e-5 * c2, -1e-5 * c2], axis=1)
    for _ in range(500):
        state, _ = model.step(state, d_eps)
    return state, d_eps


def test_tangent_only_when_asked_and_step_unchanged(model, sheared):
    state, d_eps = sheared
    plain_state, plain = model.step(state, d_eps)
    new_state, with_t = model.step(state, d_eps, with_tangent=True)
    assert plain.tangent is None
    assert with_t.tangent.shape == (d_eps.shape[0], 2, 2)
    np.testing.assert_array_equal(plain.moment, with_t.moment)
    for a, b in zip(plain_state, new_state):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("regime", ["stick", "slide"])
def test_tangent_matches_central_differences(model, sheared, regime):
    state, d_eps = sheared
    new, response = model.step(state, d_eps, with_tangent=True)
    reached = model._regime(state, new)
    loaded = reached["closed1"] > 0
    cells = np.flatnonzero(loaded & (reached["stick"] if regime == "stick" else ~reached["stick"]))
    assert cells.size >= 3, f"the fixture must hold {regime} cells"
    reference = central_difference_tangent(model, state, d_eps, 1e-8)
    error = relative_error(response.tangent[cells], reference[cells])
    assert error.max() <= 1e-5, error


def test_tangent_of_isotropic_loading_from_rest(model):
    """First increment from the touching state (every contact sticks) and a later one."""
    alpha0 = np.array([35.0, 40.0, 55.0, 60.0, 75.0])
    state = model.init_state([h_cell(a, R) for a in alpha0], alpha0.size)
    d_eps = np.full((alpha0.size, 2), 2e-4)
    for _ in range(3):
        new, response = model.step(state, d_eps, with_tangent=True)
        error = relative_error(response.tangent, central_difference_tangent(model, state, d_eps, 1e-9))
        assert error.max() <= 1e-5, error
        state = new


def test_open_cell_has_zero_tangent(model):
    """An extended cell loses all its contacts: a stress-free mechanism, zero tangent."""
    state = model.init_state(h_cell(40.0, R), 1)
    new, response = model.step(state, np.array([[-1e-2, -1e-2]]), with_tangent=True)
    assert model.observables(new)["N1"][0] == 0.0
    np.testing.assert_array_equal(response.tangent, 0.0)
