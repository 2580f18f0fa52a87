"""Analytical backend: the planar H-cell's equilibrium, contact law and kinematics, the ten-sphere cell as two
planes sharing their axial grains, the consistent tangent and the CellModel contract in both dimensions."""

import math

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.backends.analytical import Analytical3DCell, AnalyticalCell, AnalyticalState
from tangent_fd import relative_error
from warp_hcell.core.checks import central_difference_tangent
from warp_hcell.core.contract import CellModel
from warp_hcell.core.parameters import ContactLaw, HertzMindlinLaw
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.files import describe, from_description
from warp_hcell.mesostructures.hcell import h_cell, plain_h_cell
from warp_hcell.mesostructures.mesostructure import cell_measure

LAW = ContactLaw()
R = 0.5
D = 2 * R
KN, KT, MU = LAW.kn, LAW.kt, LAW.mu
DIMS = (2, 3)


@pytest.fixture
def model():
    return AnalyticalCell(LAW, R)


@pytest.fixture(scope="module")
def cells():
    """The closed form of each dimension."""
    return {dim: make_cell_model("analytical", dim=dim) for dim in DIMS}


def _h_cells(alpha0, radius=R):
    """One H-cell per opening angle [deg] (``init_state`` takes one mesostructure per cell)."""
    return [h_cell(a, radius) for a in alpha0]


def _drive(model, state, d_eps, n_increments):
    """Apply the same increment n times; returns the last state and response."""
    d_eps = np.broadcast_to(np.asarray(d_eps, dtype=float), (state.l1.size, 2))
    response = None
    for _ in range(n_increments):
        state, response = model.step(state, d_eps)
    return state, response


def _mixed_states(model):
    """Cells of several alpha0 after isotropic compression then constant-volume shear in
    several local directions (d_eps_n = delta cos 2 theta = -d_eps_t)."""
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 5)
    c2 = np.tile(np.cos(2 * np.linspace(0, np.pi / 2, 5)), 4)
    state = model.init_state(_h_cells(alpha0), alpha0.size)
    state, _ = _drive(model, state, [5e-6, 5e-6], 200)
    state, _ = _drive(model, state, np.stack([1e-5 * c2, -1e-5 * c2], axis=1), 500)
    return state


def _path(rng, n_cells, dim=3):
    """Isotropic loading, then random proportional legs with a reversal (sticking, sliding, opening)."""
    iso = [np.full((n_cells, dim), 2e-4)] * 20
    direction = rng.normal(size=(n_cells, dim))
    return iso + [3e-4 * direction] * 30 + [-3e-4 * direction] * 30


def _loaded(cell, dim, n=12, seed=0, legs=35):
    """n cells of alpha0 in [46, 70] deg (the ten-sphere cell's range) after ``legs`` increments of ``_path``."""
    rng = np.random.default_rng(seed)
    state = cell.touching_state(rng.uniform(46.0, 70.0, n), n)
    for d in _path(rng, n, dim)[:legs]:
        state, _ = cell.step(state, d)
    return state, 1e-5 * rng.normal(size=(n, dim))


def _fields(cell, state):
    """The state's arrays by name (``state_to_arrays``): one plane's fields, or both planes' prefixed."""
    return cell.state_to_arrays(state)


# -- the contract, in both dimensions ------------------------------------------------------------------------


@pytest.mark.parametrize("dim, cls", [(2, AnalyticalCell), (3, Analytical3DCell)])
def test_is_a_cell_model_and_in_the_registry(dim, cls):
    model = make_cell_model("analytical", contact_law=LAW, radius=R, dim=dim)
    assert isinstance(model, cls) and isinstance(model, CellModel)
    assert model.name == "analytical" and model.dim == dim


@pytest.mark.parametrize("dim, spec, message", [
    (2, "hcell-fines:alpha0=50,ratio=0.5", "analytical models the plain H-cell only"),
    (2, "hcell-unequal:alpha0=50,lateral=0.7", "analytical models the plain H-cell only"),
    (2, "hcell:alpha0=50,radius=1", "radius 1 m, the analytical cell 0.5 m"),
    (2, "hcell3d:alpha0=50", "is a 3D cell and this analytical backend models 2D cells"),
    (3, "hcell3d:alpha0=61,plane=80", "analytical models the plain ten-sphere H-cell only"),
    (3, "hcell3d:alpha0=61,radius=1", "spheres of radius 1 m, the analytical cell 0.5 m"),
    (3, "hcell:alpha0=61", "is a 2D cell and this analytical backend models 3D cells"),
])
def test_init_state_refuses_any_cell_but_its_plain_cell(cells, dim, spec, message):
    meso = resolve_mesostructure(spec)
    for batch in (meso, [plain_h_cell(dim, 61.0, R), meso]):
        with pytest.raises(ValueError, match=message) as info:
            cells[dim].init_state(batch, 1 if batch is meso else 2)
        assert "\n" not in str(info.value)


@pytest.mark.parametrize("dim", DIMS)
def test_volume_positions_and_initial_state_follow_the_mesostructure(cells, dim):
    meso = plain_h_cell(dim, 61.0, R)
    cell = cells[dim]
    state = cell.init_state(meso, 3)
    np.testing.assert_allclose(cell.volume(state), cell_measure(meso.position, meso.outer), rtol=1e-14)
    np.testing.assert_allclose(cell.positions(state)[0], meso.position, atol=1e-15)
    np.testing.assert_array_equal(cell.response(state).area, cell.volume(state))


@pytest.mark.parametrize("dim", DIMS)
def test_step_is_pure_and_deterministic(cells, dim):
    cell = cells[dim]
    state, d_eps = _loaded(cell, dim)
    before = {k: v.copy() for k, v in _fields(cell, state).items()}
    d_before = d_eps.copy()
    first, r1 = cell.step(state, d_eps, with_tangent=True)
    second, r2 = cell.step(state, d_eps, with_tangent=True)
    for name, value in _fields(cell, state).items():
        np.testing.assert_array_equal(value, before[name])
    np.testing.assert_array_equal(d_eps, d_before)
    a, b = _fields(cell, first), _fields(cell, second)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    np.testing.assert_array_equal(r1.moment, r2.moment)
    np.testing.assert_array_equal(r1.tangent, r2.tangent)
    assert any(not np.array_equal(a[name], before[name]) for name in a)


@pytest.mark.parametrize("dim", DIMS)
def test_take_and_arrays_round_trip_and_batch_invariance(cells, dim):
    cell = cells[dim]
    state, d_eps = _loaded(cell, dim)
    index = np.array([3, 0, 3, 11])
    sub = cell.take(state, index)
    arrays = cell.state_to_arrays(state)
    for name, value in cell.state_to_arrays(sub).items():
        np.testing.assert_array_equal(value, arrays[name][index])
    prefixes = {2: [""], 3: ["a_", "b_"]}[dim]
    assert set(arrays) == {p + f for p in prefixes for f in AnalyticalState._fields}
    restored = cell.state_from_arrays(arrays)
    full, again, part = state, restored, sub
    for _ in range(50):
        full, _ = cell.step(full, d_eps)
        again, _ = cell.step(again, d_eps)
        part, _ = cell.step(part, d_eps[index])
    f, g, p = (cell.state_to_arrays(s) for s in (full, again, part))
    for name in f:
        np.testing.assert_array_equal(f[name], g[name])
        np.testing.assert_array_equal(f[name][index], p[name])  # a cell ignores the rest of its batch
    arrays[prefixes[0] + "T1"][:] = 1.0  # the snapshot is a copy
    assert not np.any(cell.state_to_arrays(state)[prefixes[0] + "T1"] == 1.0)


@pytest.mark.parametrize("dim", DIMS)
def test_tangent_only_when_asked_and_step_unchanged(cells, dim):
    cell = cells[dim]
    state, d_eps = _loaded(cell, dim)
    plain_state, plain = cell.step(state, d_eps)
    new_state, with_t = cell.step(state, d_eps, with_tangent=True)
    assert plain.tangent is None
    assert with_t.tangent.shape == (d_eps.shape[0], dim, dim)
    np.testing.assert_array_equal(plain.moment, with_t.moment)
    a, b = _fields(cell, plain_state), _fields(cell, new_state)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])


@pytest.mark.parametrize("dim", DIMS)
def test_the_tangent_equals_central_differences(cells, dim):
    cell = cells[dim]
    state, d_eps = _loaded(cell, dim, n=8, seed=1)
    _, response = cell.step(state, d_eps, with_tangent=True)
    fd = central_difference_tangent(cell, state, d_eps, 1e-9)
    scale = np.abs(fd).max(axis=(1, 2), keepdims=True)
    assert np.abs(response.tangent - fd).max() / scale.min() < 1e-5


@pytest.mark.parametrize("dim, alpha0", [(2, [35.0, 40.0, 55.0, 60.0, 75.0]), (3, [46.0, 50.0, 55.0, 60.0, 75.0])])
def test_tangent_of_isotropic_loading_from_rest(cells, dim, alpha0):
    """First increment from the touching state (every contact sticks) and a later one."""
    cell = cells[dim]
    state = cell.init_state([plain_h_cell(dim, a, R) for a in alpha0], len(alpha0))
    d_eps = np.full((len(alpha0), dim), 2e-4)
    for _ in range(3):
        new, response = cell.step(state, d_eps, with_tangent=True)
        error = relative_error(response.tangent, central_difference_tangent(cell, state, d_eps, 1e-9))
        assert error.max() <= 1e-5, error
        state = new


@pytest.mark.parametrize("dim", DIMS)
def test_open_cell_has_zero_tangent(cells, dim):
    """An extended cell loses all its contacts: a stress-free mechanism, zero tangent."""
    cell = cells[dim]
    state = cell.init_state(plain_h_cell(dim, 50.0, R), 1)
    new, response = cell.step(state, np.full((1, dim), -1e-2), with_tangent=True)
    obs = cell.observables(new)
    assert not any(obs[name][0] for name in obs if name.startswith("closed"))
    np.testing.assert_array_equal(response.tangent, 0.0)
    np.testing.assert_array_equal(response.moment, 0.0)


# -- the planar H-cell -----------------------------------------------------------------------------------------


def test_init_state_is_touching_and_force_free(model):
    alpha0 = np.array([30.0, 40.0, 55.0, 60.0, 89.9])
    state = model.init_state(_h_cells(alpha0), alpha0.size)
    obs = model.observables(state)
    a = np.radians(alpha0)
    np.testing.assert_allclose(obs["d1"], D)
    np.testing.assert_allclose(obs["d2"], D)
    np.testing.assert_allclose(obs["l1"], D * (1 + 2 * np.cos(a)), rtol=1e-15)
    np.testing.assert_allclose(obs["l2"], 2 * D * np.sin(a), rtol=1e-15)
    np.testing.assert_allclose(obs["alpha_deg"], alpha0, rtol=1e-14)
    for name in ("N1", "N2", "T1"):
        assert np.all(obs[name] == 0.0), name
    # at 30 deg grains 2-6 touch: l2 = D to rounding, so S_tt is zero to kn * ulp(D) * D
    np.testing.assert_allclose(np.stack([obs["S_nn"], obs["S_tt"]]), 0.0, atol=1e-14 * KN * D * D)
    assert not obs["closed1"].any() and not obs["closed2"].any()
    np.testing.assert_allclose(obs["area"], 2 * D * np.sin(a) * D * (1 + np.cos(a)), rtol=1e-14)
    scalar = model.init_state(h_cell(55.0, R), 3)
    assert scalar.l1.shape == (3,) and np.all(scalar.alpha == np.radians(55.0))


def test_alpha0_comes_from_the_geometry_of_the_mesostructure(model):
    """A plain H-cell read back from its description (not built here) starts at its own angle."""
    meso = from_description(describe(h_cell(47.5, R)))
    state = model.init_state(meso, 2)
    assert np.all(state.alpha == np.radians(47.5))


@pytest.mark.parametrize("alpha0, slides", [(40.0, False), (55.0, True)])
def test_first_increment_matches_the_linearised_cell(model, alpha0, slides):
    """Axial compression eps at constant width from the touching state, to first order:
    the axial shortening splits between contact 2-3 (stiffness 2 kn along n) and the type-1
    contacts (K = kn cos^2 + kt sin^2 when stuck, kn cos (cos + mu sin) when sliding)."""
    eps = 1e-7
    state = model.init_state(h_cell(alpha0, R), 1)
    state, _ = model.step(state, np.array([[eps, 0.0]]))
    c, s = math.cos(math.radians(alpha0)), math.sin(math.radians(alpha0))
    K = KN * c * (c + MU * s) if slides else KN * c * c + KT * s * s
    l1 = D * (1 + 2 * c)
    du = -0.5 * eps * l1 * 2 * KN / (2 * KN + K)  # change of l1/2 - y2
    dy2 = -0.5 * eps * l1 - du
    N1 = -KN * c * du
    T1 = MU * N1 if slides else -KT * s * du
    np.testing.assert_allclose(state.N1, N1, rtol=1e-5)
    np.testing.assert_allclose(state.N2, -2 * KN * dy2, rtol=1e-5)
    np.testing.assert_allclose(state.T1, T1, rtol=1e-5)


def test_stick_slip_threshold_of_the_constant_width_compression(model):
    """T1/N1 = (kt/kn) tan(alpha) while stuck: sliding at once iff tan(alpha0) > mu kn/kt."""
    threshold = math.degrees(math.atan(MU * KN / KT))
    state = model.init_state(_h_cells([threshold - 0.1, threshold + 0.1]), 2)
    state, _ = _drive(model, state, [1e-6, 0.0], 5)
    ratio = state.T1 / state.N1
    assert ratio[0] < MU * (1 - 1e-4)
    np.testing.assert_allclose(ratio[1], MU, rtol=1e-12)


def test_axial_compression_at_constant_width(model):
    """The axis shortens, alpha grows (opening), so friction resists with T1 > 0: the loose
    55-deg cell slides at T1 = +mu N1 all along, the 40-deg cell stays stuck to 5 %."""
    state = model.init_state(_h_cells([55.0, 40.0]), 2)
    alpha_prev = state.alpha
    for _ in range(10):
        state, response = _drive(model, state, [1e-3 / 10, 0.0], 50)
        assert np.all(state.alpha > alpha_prev)
        alpha_prev = state.alpha
        assert np.all(state.N1 > 0) and np.all(state.N2 > 0)
        np.testing.assert_allclose(state.T1[0], MU * state.N1[0], rtol=1e-12)
        assert 0 < state.T1[1] < MU * state.N1[1] * 0.95
        assert np.all(response.moment[:, 0, 0] > response.moment[:, 1, 1])


def test_equilibrium_and_moment_identities(model):
    """N2 = N1 cos a + T1 sin a; S_nn = F1 l1 and S_tt = 2 F2 l2 (spec sections 5, 7)."""
    state = _mixed_states(model)
    obs = model.observables(state)
    a = np.radians(obs["alpha_deg"])
    c, s = np.cos(a), np.sin(a)
    assert obs["closed1"].any() and (~obs["closed2"]).any()  # loaded and opened cells
    scale = KN * R
    np.testing.assert_allclose(obs["N2"], obs["N1"] * c + obs["T1"] * s, rtol=0, atol=1e-9 * scale)
    F1 = 2 * (obs["N1"] * c + obs["T1"] * s)
    F2 = obs["N1"] * s - obs["T1"] * c
    assert np.all(obs["l1"] > D) and np.all(obs["l2"] > D)  # no extra contacts here
    np.testing.assert_allclose(obs["S_nn"], F1 * obs["l1"], rtol=1e-10, atol=1e-8 * scale)
    np.testing.assert_allclose(obs["S_tt"], 2 * F2 * obs["l2"], rtol=1e-10, atol=1e-8 * scale)
    assert np.all(np.abs(obs["T1"]) <= MU * obs["N1"] * (1 + 1e-12))
    assert np.all(obs["N1"][~obs["closed1"]] == 0) and np.all(obs["T1"][~obs["closed1"]] == 0)


def test_extended_axis_closes_the_cell_until_it_is_stress_free(model):
    """After isotropic compression, extending the axis at constant width closes alpha:
    friction turns negative (T1 >= -mu N1), then 2-3 opens and, below 60 deg, N1 = 0 too."""
    state = model.init_state(_h_cells([55.0, 40.0, 35.0]), 3)
    state, _ = _drive(model, state, [1e-5, 1e-5], 200)
    assert np.all(state.N1 > 0) and np.all(state.T1 > 0)
    state, _ = _drive(model, state, [-1e-5, 0.0], 200)
    assert np.all(state.T1 < 0) and np.all(state.T1 >= -MU * state.N1 * (1 + 1e-12))
    state, response = _drive(model, state, [-1e-5, 0.0], 800)
    assert np.all(np.degrees(state.alpha) < 60)
    for name in ("N1", "N2", "T1"):
        assert np.all(getattr(state, name) == 0.0), name
    assert np.all(response.moment == 0.0)
    obs = model.observables(state)
    assert not obs["closed1"].any() and not obs["closed2"].any()


def test_open_cell_keeps_y2(model):
    state = model.init_state(_h_cells([40.0, 55.0, 80.0]), 3)
    new, response = _drive(model, state, [-1e-4, -2e-4], 10)
    np.testing.assert_array_equal(new.y2, state.y2)
    assert np.all(response.moment == 0.0)


def test_increment_size_independence(model):
    """1e-5 and 2e-6 increments agree to 4 digits along a constant-volume local path."""
    alpha0 = np.repeat([35.0, 40.0, 55.0], 4)
    c2 = np.tile([1.0, 0.5, -0.5, -1.0], 3)
    results = []
    for delta in (1e-5, 2e-6):
        state = model.init_state(_h_cells(alpha0), alpha0.size)
        state, _ = _drive(model, state, [delta, delta], round(1e-3 / delta))
        state, response = _drive(model, state, np.stack([delta * c2, -delta * c2], axis=1), round(0.03 / delta))
        results.append((state, response))
    (coarse, r_coarse), (fine, r_fine) = results
    assert (fine.N1 > 0).sum() >= 6 and (fine.N1 == 0).sum() >= 2
    for name in ("N1", "N2", "T1"):
        a, b = getattr(coarse, name), getattr(fine, name)
        assert np.abs(a - b).max() <= 1e-4 * np.abs(b).max(), name
    assert np.abs(r_coarse.moment - r_fine.moment).max() <= 1e-4 * np.abs(r_fine.moment).max()


def test_grain_size_drops_out(model):
    """sigma/kn against strain does not depend on the radius (spec section 1)."""
    big = AnalyticalCell(LAW, 2 * R)
    d_eps = np.array([[2e-5, -1e-5], [1e-5, 1e-5]])
    a, b = model.init_state(_h_cells([40.0, 55.0]), 2), big.init_state(_h_cells([40.0, 55.0], 2 * R), 2)
    for _ in range(300):
        a, ra = model.step(a, d_eps)
        b, rb = big.step(b, d_eps)
    np.testing.assert_allclose(rb.moment / rb.area[:, None, None], ra.moment / ra.area[:, None, None], rtol=1e-8, atol=1e-3)


def test_g2_variant_changes_the_equilibrium():
    g2 = 0.3
    model = AnalyticalCell(LAW, R, g2=g2)
    state = _mixed_states(model)
    c, s = np.cos(state.alpha), np.sin(state.alpha)
    np.testing.assert_allclose(state.N2, state.N1 * c + state.T1 * s + g2 * state.T1, rtol=0, atol=1e-9 * KN * R)
    assert np.abs(g2 * state.T1).max() > 1e3


def test_observables_names_and_positions(model):
    state = _mixed_states(model)
    obs = model.observables(state)
    names = {"l1", "l2", "d1", "d2", "alpha_deg", "N1", "N2", "T1", "S_nn", "S_tt", "area", "closed1", "closed2"}
    names |= {f"x_{axis}{i}" for i in range(1, 7) for axis in "nt"}
    assert set(obs) == names
    assert all(value.shape == (state.l1.size,) for value in obs.values())
    np.testing.assert_allclose(obs["x_n1"] - obs["x_n4"], obs["l1"], rtol=1e-14)
    np.testing.assert_allclose(obs["x_n2"] - obs["x_n3"], obs["d2"], rtol=1e-14)
    np.testing.assert_allclose(np.hypot(obs["x_n1"] - obs["x_n2"], obs["x_t1"] - obs["x_t2"]), obs["d1"], rtol=1e-13)


def test_friction_locked_cell_whose_type2_contact_opens(model):
    """alpha > 60 deg, axis extended and width compressed from the touching state: 2-3
    opens and grain 2 hangs on friction, T1 = -N1 cot(alpha) with |T1| < mu N1. There f grows
    with y2 where the contact slides back, yet the solve needs few iterations."""
    state = model.init_state(_h_cells([70.0, 80.0, 85.0]), 3)
    new, response = model.step(state, np.array([[-7e-7, 3e-7]] * 3))
    assert response.diagnostics["iterations"] <= 8 and response.diagnostics["n_unconverged"] == 0
    assert np.all(new.N2 == 0.0) and np.all(new.N1 > 0.0)
    np.testing.assert_allclose(new.T1, -new.N1 / np.tan(new.alpha), rtol=1e-6)
    assert np.all(np.abs(new.T1) < MU * new.N1)


def test_cell_held_at_alpha_90_when_no_equilibrium_exists_below(model):
    """alpha0 = 89.5 deg compressed along its axis: once l1 < D (grains 1-4 touch), 2-3
    pushes grain 2 past alpha = 90 deg, outside the H-model; the cell stays at the limit,
    flagged, and its moment carries the 1-4 contact."""
    state = model.init_state(_h_cells([89.5, 60.0]), 2)
    for _ in range(20):
        state, response = model.step(state, np.array([[1e-3, 0.0], [1e-3, 0.0]]))
        assert response.diagnostics["iterations"] <= 6 and response.diagnostics["n_unconverged"] == 0
    assert response.diagnostics["n_alpha_limit"] == 1
    assert state.alpha[0] == np.pi / 2 and state.alpha[1] < np.pi / 2
    l1, d2 = state.l1[0], 2 * state.y2[0]
    assert l1 < D and d2 == l1
    np.testing.assert_allclose(response.moment[0, 0, 0], 2 * state.N2[0] * d2 + KN * (D - l1) * l1, rtol=1e-12)


@pytest.fixture(scope="module")
def sheared():
    """Cells of alpha0 35-70 deg, isotropically compressed then sheared at constant volume
    in five local directions: a mix of sticking, sliding and open type-1 contacts."""
    model = AnalyticalCell(LAW, R)
    alpha0 = np.repeat([35.0, 40.0, 55.0, 70.0], 5)
    c2 = np.tile(np.cos(2 * np.linspace(0, np.pi / 2, 5)), 4)
    state = model.init_state(_h_cells(alpha0), alpha0.size)
    for _ in range(200):
        state, _ = model.step(state, np.full((alpha0.size, 2), 5e-6))
    d_eps = np.stack([1e-5 * c2, -1e-5 * c2], axis=1)
    for _ in range(500):
        state, _ = model.step(state, d_eps)
    return model, state, d_eps


@pytest.mark.parametrize("regime", ["stick", "slide"])
def test_tangent_matches_central_differences_in_stick_and_in_slide(sheared, regime):
    model, state, d_eps = sheared
    new, response = model.step(state, d_eps, with_tangent=True)
    reached = model._regime(state, new)
    loaded = reached["closed1"] > 0
    cells = np.flatnonzero(loaded & (reached["stick"] if regime == "stick" else ~reached["stick"]))
    assert cells.size >= 3, f"the fixture must hold {regime} cells"
    reference = central_difference_tangent(model, state, d_eps, 1e-8)
    error = relative_error(response.tangent[cells], reference[cells])
    assert error.max() <= 1e-5, error


# -- the ten-sphere cell: two planes sharing their axial grains ------------------------------------------------


def _plane_cases():
    """(alpha0 [deg], increments) of 12 cells on random legs, and of two cells compressed along the axis until
    grains 1 and 4 touch (l1 < D)."""
    rng = np.random.default_rng(0)
    return {"random legs": (np.round(rng.uniform(46.0, 70.0, 12), 6), _path(rng, 12)),
            "axis compressed": (np.array([85.0, 88.0]), [np.array([[1e-2, 0.0, 0.0]] * 2)] * 20)}


@pytest.mark.parametrize("case", ["random legs", "axis compressed"])
def test_each_plane_is_the_planar_cell_and_the_axial_contact_counts_once(cells, case):
    cell3, cell2 = cells[3], cells[2]
    alpha0, path = _plane_cases()[case]
    n = alpha0.size
    state3 = cell3.init_state([resolve_mesostructure(f"hcell3d:alpha0={float(a)!r}") for a in alpha0], n)
    meso2 = [resolve_mesostructure(f"hcell:alpha0={float(a)!r}") for a in alpha0]
    plane_a, plane_b = cell2.init_state(meso2, n), cell2.init_state(meso2, n)
    for d in path:
        state3, r3 = cell3.step(state3, d)
        plane_a, ra = cell2.step(plane_a, d[:, [0, 1]])
        plane_b, rb = cell2.step(plane_b, d[:, [0, 2]])
        axial = 2e8 * np.maximum(1.0 - plane_a.l1, 0.0) * plane_a.l1
        np.testing.assert_array_equal(r3.moment[:, 0, 0], ra.moment[:, 0, 0] + rb.moment[:, 0, 0] - axial)
        np.testing.assert_array_equal(r3.moment[:, 1, 1], ra.moment[:, 1, 1])
        np.testing.assert_array_equal(r3.moment[:, 2, 2], rb.moment[:, 1, 1])
        assert np.all(r3.moment[:, [0, 0, 1], [1, 2, 2]] == 0.0)
    if case == "random legs":
        assert (ra.moment[:, 0, 0] != rb.moment[:, 0, 0]).all()  # the planes were driven differently
    else:
        assert np.all(axial > 0.0)  # grains 1 and 4 touch
        _, response = cell3.step(state3, d, with_tangent=True)
        np.testing.assert_allclose(response.tangent, central_difference_tangent(cell3, state3, d, 1e-9), rtol=1e-5)


def test_cells_whose_planes_meet_are_counted(cells):
    """Lateral compression of both planes from 46 deg closes the gap between the planes' lateral grains; a
    planar cell has no second plane to meet."""
    cell3 = cells[3]
    state = cell3.touching_state(46.0, 1)
    counts = []
    for _ in range(120):
        state, response = cell3.step(state, np.array([[0.0, 2e-4, 2e-4]]))
        counts.append(response.diagnostics["n_cross_plane"])
    assert counts[0] == 0 and counts[-1] == 1
    assert 0.25 * (state.a.l2[0] ** 2 + state.b.l2[0] ** 2) + (state.a.y2[0] - state.b.y2[0]) ** 2 < 1.0
    assert cell3.observables(state)["cross_plane"][0]
    _, planar = cells[2].step(cells[2].touching_state(46.0, 1), np.array([[0.0, 2e-4]]))
    assert "n_cross_plane" not in planar.diagnostics


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
