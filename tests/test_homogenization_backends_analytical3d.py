"""Closed-form ten-sphere cell: two planar H-cells sharing their axial grains (docs/model.md section 14)."""

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.backends.analytical3d import Analytical3DCell
from warp_hcell.core.checks import central_difference_tangent
from warp_hcell.core.parameters import ContactLaw, HertzMindlinLaw
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.mesostructure import cell_measure


@pytest.fixture(scope="module")
def cells():
    return make_cell_model("analytical", dim=3), make_cell_model("analytical")


def _path(rng, n_cells):
    """Isotropic loading, then random proportional legs with a reversal (sticking, sliding, opening)."""
    iso = [np.full((n_cells, 3), 2e-4)] * 20
    direction = rng.normal(size=(n_cells, 3))
    return iso + [3e-4 * direction] * 30 + [-3e-4 * direction] * 30


def test_each_plane_is_the_planar_cell_and_the_axial_contact_counts_once(cells):
    cell3, cell2 = cells
    rng = np.random.default_rng(0)
    n = 12
    alpha0 = np.round(rng.uniform(46.0, 70.0, n), 6)
    state3 = cell3.init_state([resolve_mesostructure(f"hcell3d:alpha0={float(a)!r}") for a in alpha0], n)
    meso2 = [resolve_mesostructure(f"hcell:alpha0={float(a)!r}") for a in alpha0]
    plane_a, plane_b = cell2.init_state(meso2, n), cell2.init_state(meso2, n)
    for d in _path(rng, n):
        state3, r3 = cell3.step(state3, d)
        plane_a, ra = cell2.step(plane_a, d[:, [0, 1]])
        plane_b, rb = cell2.step(plane_b, d[:, [0, 2]])
        axial = 2e8 * np.maximum(1.0 - plane_a.l1, 0.0) * plane_a.l1
        np.testing.assert_array_equal(r3.moment[:, 0, 0], ra.moment[:, 0, 0] + rb.moment[:, 0, 0] - axial)
        np.testing.assert_array_equal(r3.moment[:, 1, 1], ra.moment[:, 1, 1])
        np.testing.assert_array_equal(r3.moment[:, 2, 2], rb.moment[:, 1, 1])
        assert np.all(r3.moment[:, [0, 0, 1], [1, 2, 2]] == 0.0)
    assert (ra.moment[:, 0, 0] != rb.moment[:, 0, 0]).all()  # the planes were driven differently


def test_the_tangent_equals_central_differences(cells):
    cell3, _ = cells
    rng = np.random.default_rng(1)
    n = 8
    state = cell3.touching_state(rng.uniform(46.0, 70.0, n), n)
    for d in _path(rng, n)[:35]:
        state, _ = cell3.step(state, d)
    d = 1e-5 * rng.normal(size=(n, 3))
    _, response = cell3.step(state, d, with_tangent=True)
    h = 1e-9
    fd = central_difference_tangent(cell3, state, d, h)
    scale = np.abs(fd).max(axis=(1, 2), keepdims=True)
    assert np.abs(response.tangent - fd).max() / scale.min() < 1e-5


def test_volume_and_initial_state_follow_the_mesostructure(cells):
    cell3, _ = cells
    meso = resolve_mesostructure("hcell3d:alpha0=61")
    state = cell3.init_state(meso, 3)
    np.testing.assert_allclose(cell3.volume(state), cell_measure(meso.position, meso.outer), rtol=1e-14)
    np.testing.assert_allclose(cell3.positions(state)[0], meso.position, atol=1e-15)
    with pytest.raises(ValueError, match="plain ten-sphere H-cell"):
        cell3.init_state(resolve_mesostructure("hcell3d:alpha0=61,plane=80"), 3)
    with pytest.raises(ValueError, match="radius"):
        Analytical3DCell(ContactLaw(), 0.25).init_state(meso, 1)


def test_cells_whose_planes_meet_are_counted(cells):
    """Lateral compression of both planes from 46 deg closes the gap between the planes' lateral grains."""
    cell3, _ = cells
    state = cell3.touching_state(46.0, 1)
    counts = []
    for _ in range(120):
        state, response = cell3.step(state, np.array([[0.0, 2e-4, 2e-4]]))
        counts.append(response.diagnostics["n_cross_plane"])
    assert counts[0] == 0 and counts[-1] == 1
    assert 0.25 * (state.a.l2[0] ** 2 + state.b.l2[0] ** 2) + (state.a.y2[0] - state.b.y2[0]) ** 2 < 1.0


def test_the_hertz_mindlin_tangent_equals_central_differences():
    """The consistent tangent of the Hertz-Mindlin closed form (overlap-dependent normal and tangential
    stiffness) against central differences of its own step, from states with sticking and sliding
    type-1 contacts and an open type-2 contact (solve tolerance 1e-14: the default 1e-10 moves y2
    by about the stencil's own displacement)."""
    cell3 = make_cell_model("analytical", dim=3, contact_law=HertzMindlinLaw(), tolerance=1e-14)
    rng = np.random.default_rng(3)
    n = 8
    state = cell3.touching_state(rng.uniform(46.0, 70.0, n), n)
    for d in _path(rng, n)[:35]:
        state, _ = cell3.step(state, 0.1 * d)
    d = 1e-6 * rng.normal(size=(n, 3))
    _, response = cell3.step(state, d, with_tangent=True)
    h = 1e-10
    fd = central_difference_tangent(cell3, state, d, h)
    scale = np.abs(fd).max(axis=(1, 2), keepdims=True)
    assert np.abs(response.tangent - fd).max() / scale.min() < 5e-6  # measured 1.4e-6
    assert response.diagnostics["n_unconverged"] == 0


def test_hertz_mindlin_cells_of_a_population_equal_one_cell_backends():
    G, nu, phi = np.array([10e9, 29e9, 45e9]), np.array([0.1, 0.2, 0.3]), np.array([20.0, 30.0, 35.0])
    alpha0 = np.array([50.0, 60.0, 70.0])
    population = Analytical3DCell.with_hertz_cell_laws(G, nu, phi, 0.5, alpha0_deg=alpha0)
    state = population.touching_state(alpha0, 3)
    singles = [make_cell_model("analytical", dim=3, contact_law=HertzMindlinLaw(g, v, p))
               for g, v, p in zip(G, nu, phi)]
    single_states = [m.touching_state(a, 1) for m, a in zip(singles, alpha0)]
    for d in [np.full(3, 1e-4)] * 5 + [np.array([2e-4, -1e-4, -1e-4])] * 20:
        state, response = population.step(state, np.tile(d, (3, 1)))
        for k, model in enumerate(singles):
            single_states[k], single = model.step(single_states[k], d[None])
            np.testing.assert_array_equal(response.moment[k], single.moment[0])
    with pytest.raises(ValueError, match="poisson"):
        Analytical3DCell.with_hertz_cell_laws(G, np.array([0.1, 0.6, 0.2]), phi, 0.5)
