"""Condensed tangent of DEM cells (any mesostructure) against central differences of the step.

The DEM step is a damped dynamic relaxation driven at a fixed strain per substep along the
largest strain component: substep k reaches s_k = k rate / max |d_eps| of the increment, the
last one is shorter (``warp_hcell.dem.kernels``). Its differences are taken with a tight
equilibrium tolerance, slow driving (strain_per_substep = refined_strain_per_substep, so no
adaptive rate decision), max |d_eps| half a substep from an integer count and no tie between
|d_eps_n| and |d_eps_t| (max |d_eps| has a kink there: the probe increment is the next
constant-volume increment with its t component 1.1 times larger).

Sticking contacts: the step's own central differences (``central_difference_tangent``) match the condensed
tangent to <= 1e-5. Sliding contacts depend on the size of every driving substep: a
difference step along the largest component changes the last driving substep by the step
itself, and the step's slope along that component differs from the quasi-static one by 0.25
to 2.6 % in slide, at any driving rate (a property of the stepping: docs/bvp.md section 1,
studies/bench_dem_tangent.py). Sliding cells are therefore checked with differences at a
held driving schedule (``fd_tangent_fixed_schedule``: the rate follows max |d_eps| over the
stencil, so the s_k stay those of the increment); what remains falls with the driving rate
(|T| / mu N ends a hair below 1 after the last relaxation swings): 4.0e-5 to 1.2e-4 at 1e-8
strain per substep, 2.2e-6 to 9.4e-6 at 1e-9 (other probe directions: up to 3.8e-4 and
2.8e-5, on a 55 deg cell with a weak contact). The condensed tangent is the quasi-static
limit: it agrees with the analytical cell's implicit tangent to 1e-9 in slide.
"""

import numpy as np
import pytest

from homogenization.backends.analytical import AnalyticalCell
from tangent_fd import fd_tangent_fixed_schedule, relative_error
from warp_hcell.core.checks import central_difference_tangent
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.dem.tangent import condensed_tangent, sliding_contacts

LAW = ContactLaw()
R = 0.5
TIGHT = DemSettings(force_tolerance=1e-13, strain_per_substep=1e-8, refined_strain_per_substep=1e-8, max_substeps=10**7)
DATA = "warp_hcell/data"


def _sheared(model, alpha0, n_cells, iso=1e-3, cells=None):
    """Cells compressed isotropically, then sheared at constant volume in several directions (those of
    ``n_cells`` cells; ``cells``: an index array that keeps only those cells of ``alpha0`` and the directions)."""
    c2 = np.cos(2 * np.linspace(0, np.pi / 2, n_cells))
    if cells is not None:
        alpha0, c2, n_cells = np.asarray(alpha0)[cells], c2[cells], len(cells)
    state = model.init_state([h_cell(a, R) for a in alpha0], n_cells)
    state, _ = model.step(state, np.full((n_cells, 2), iso))
    d_eps = np.stack([1e-3 * c2, -1e-3 * c2], axis=1)
    for _ in range(3):
        state, _ = model.step(state, d_eps)
    return state, 1e-2 * d_eps


@pytest.fixture(scope="module")
def h_cells():
    dem = DemCell(LAW, R, settings=TIGHT, threads=1)
    analytical = AnalyticalCell(LAW, R)
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 3)
    dem_state, d_eps = _sheared(dem, alpha0, alpha0.size)
    ana_state, _ = _sheared(analytical, alpha0, alpha0.size)
    return dem, dem_state, analytical, ana_state, d_eps


def _sliding_cells(dem, state, new):
    before, after = state.dem.to_numpy(), new.dem.to_numpy()
    sliding = sliding_contacts(before["position"], after["position"], state.model.radius.numpy(),
                               state.model.meso.pairs, before["shear_force"], kn=LAW.kn, kt=LAW.kt, mu=LAW.mu)
    return sliding.any(axis=1), after["contact"].sum(axis=1) > 0


def _fixed_driving(d_eps, strain_per_substep):
    """Rescale each cell's increment so that max |d_eps| sits half a substep between integers."""
    largest = np.abs(d_eps).max(axis=1)
    return d_eps * ((np.floor(largest / strain_per_substep) + 0.5) * strain_per_substep / largest)[:, None]


def _probe(d_eps, strain_per_substep):
    """The next constant-volume increment, t component 1.1 times larger (no tie in max |d_eps|)."""
    return _fixed_driving(d_eps * np.array([1.0, 1.1]), strain_per_substep)


def test_h_cell_stick_and_slide(h_cells):
    dem, state, analytical, ana_state, d_eps = h_cells
    d_eps = _probe(d_eps, TIGHT.strain_per_substep)
    new, response = dem.step(state, d_eps, with_tangent=True)
    _, ana = analytical.step(ana_state, d_eps, with_tangent=True)
    sliding, loaded = _sliding_cells(dem, state, new)
    stick, slide = loaded & ~sliding, loaded & sliding
    assert stick.sum() >= 3 and slide.sum() >= 3
    h = 0.1 * TIGHT.strain_per_substep
    error = relative_error(response.tangent, central_difference_tangent(dem, state, d_eps, h))
    assert error[stick].max() <= 1e-5, error
    held = relative_error(response.tangent, fd_tangent_fixed_schedule(dem, state, d_eps, h))
    assert held[stick].max() <= 1e-5, held
    assert held[slide].max() <= 3e-4, held
    agreement = relative_error(response.tangent, ana.tangent)
    assert agreement[slide].max() <= 1e-8, agreement
    assert agreement[stick].max() <= 1e-6, agreement  # the DEM and analytical states differ by ~1e-7


def test_h_cell_slide_approaches_the_condensed_tangent_as_driving_slows(h_cells):
    """Ten times slower driving: the slope of the step in slide comes within 3e-5 (from ~1e-4). Only the cells of
    ``h_cells`` that slide at this driving are run (35 deg in its first three directions, 40 and 55 deg in one)."""
    slow = DemSettings(force_tolerance=1e-13, strain_per_substep=1e-9, refined_strain_per_substep=1e-9,
                       max_substeps=10**8)
    dem = DemCell(LAW, R, settings=slow, threads=1)
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 3)
    state, d_eps = _sheared(dem, alpha0, alpha0.size, cells=np.array([0, 1, 2, 3, 8]))
    d_eps = _probe(d_eps, slow.strain_per_substep)
    new, response = dem.step(state, d_eps, with_tangent=True)
    sliding, loaded = _sliding_cells(dem, state, new)
    assert (loaded & sliding).sum() >= 3
    held = fd_tangent_fixed_schedule(dem, state, d_eps, 0.1 * slow.strain_per_substep)
    error = relative_error(response.tangent, held)
    assert error[loaded & sliding].max() <= 3e-5, error


def test_tangent_only_when_asked(h_cells):
    dem, state, _, _, d_eps = h_cells
    _, plain = dem.step(state, d_eps)
    _, with_t = dem.step(state, d_eps, with_tangent=True)
    assert plain.tangent is None
    np.testing.assert_array_equal(plain.moment, with_t.moment)


@pytest.mark.parametrize("name", ["h_cell_lateral_0.7D", "h_cell_fine_grain"])
def test_generic_mesostructure_sticking(name):
    """Unequal radii and a free fine grain (free along n and t): first increments from rest stick."""
    meso = load_mesostructure(f"{DATA}/{name}.toml")
    dem = DemCell(LAW, R, settings=TIGHT, threads=1)
    state = dem.init_state(meso, 3)
    state, _ = dem.step(state, np.full((3, 2), 2e-3))
    d_eps = _fixed_driving(np.array([[1e-5, 1e-5], [2e-5, 1e-5], [1e-5, 2e-5]]), TIGHT.strain_per_substep)
    new, response = dem.step(state, d_eps, with_tangent=True)
    sliding, loaded = _sliding_cells(dem, state, new)
    assert loaded.all() and not sliding.any()
    error = relative_error(response.tangent, central_difference_tangent(dem, state, d_eps, 0.1 * TIGHT.strain_per_substep))
    assert error.max() <= 1e-5, error


def test_condensation_of_a_two_grain_chain_closed_form():
    """Grain 0 driven along n, grain 1 free along n and held by a driven grain 2: two springs
    in series, S_nn = F x summed over driven DOFs; compare with kn/2 series stiffness."""
    kn, D = 2e8, 1.0
    overlap = 1e-3
    position = np.array([[[0.0, 0.0], [D - overlap, 0.0], [2 * (D - overlap), 0.0]]])
    radius = np.full((1, 3), 0.5)
    pairs = np.array([[0, 1], [1, 2]])
    driven = np.array([[True, True], [False, True], [True, True]])
    # driven x_n moves as -x_ref per unit eps_n about grain 0 (x_ref = current position here)
    drive_rate = np.zeros((1, 3, 2))
    drive_rate[0, 2, 0] = -position[0, 2, 0]
    C = condensed_tangent(position, radius, pairs, driven, np.zeros((1, 2)), np.zeros((1, 2), bool), drive_rate,
                          kn=kn, kt=0.5 * kn, mu=0.5)
    # S_nn = F2 x2 with F2 = kn overlap / ... : dS_nn/d eps_n = (kn/2) x2^2 + F2 * dx2/d eps_n
    x2 = position[0, 2, 0]
    force = kn * overlap  # compression: each spring carries kn * overlap; F on grain 2 along +n
    expected = 0.5 * kn * x2 * x2 - force * x2
    np.testing.assert_allclose(C[0, 0, 0], expected, rtol=1e-12)
    assert C[0, 1, 0] == 0.0 and C[0, 0, 1] == 0.0
