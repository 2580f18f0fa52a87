"""Analytical H-cell backend: equilibrium, contact law, kinematics and the CellModel contract."""

import math

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.backends.analytical import AnalyticalCell, AnalyticalState
from homogenization.backends.analytical3d import Analytical3DCell
from warp_hcell.core.contract import CellModel
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.files import describe, from_description
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import ContactLaw

LAW = ContactLaw()
R = 0.5
D = 2 * R
KN, KT, MU = LAW.kn, LAW.kt, LAW.mu


@pytest.fixture
def model():
    return AnalyticalCell(LAW, R)


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


@pytest.mark.parametrize("dim, cls", [(2, AnalyticalCell), (3, Analytical3DCell)])
def test_is_a_cell_model_and_in_the_registry(dim, cls):
    model = make_cell_model("analytical", contact_law=LAW, radius=R, dim=dim)
    assert isinstance(model, cls) and isinstance(model, CellModel)
    assert model.name == "analytical"


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


@pytest.mark.parametrize("spec, message", [
    ("hcell-fines:alpha0=50,ratio=0.5", "analytical models the plain H-cell only"),
    ("hcell-unequal:alpha0=50,lateral=0.7", "analytical models the plain H-cell only"),
    ("hcell:alpha0=50,radius=1", "radius 1 m, the analytical cell 0.5 m"),
])
def test_init_state_refuses_any_cell_but_its_plain_h_cell(model, spec, message):
    meso = resolve_mesostructure(spec)
    for cells in (meso, [h_cell(50.0, R), meso]):
        with pytest.raises(ValueError, match=message) as info:
            model.init_state(cells, 1 if cells is meso else 2)
        assert "\n" not in str(info.value)


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


def test_step_is_pure_and_deterministic(model):
    state = _mixed_states(model)
    before = [field.copy() for field in state]
    d_eps = np.full((state.l1.size, 2), [2e-5, -1e-5])
    d_before = d_eps.copy()
    first, r1 = model.step(state, d_eps)
    second, r2 = model.step(state, d_eps)
    for old, field in zip(before, state):
        np.testing.assert_array_equal(field, old)
    np.testing.assert_array_equal(d_eps, d_before)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(r1.moment, r2.moment)
    assert any(not np.array_equal(a, b) for a, b in zip(first, state))


def test_take_and_arrays_round_trip_and_batch_invariance(model):
    state = _mixed_states(model)
    index = np.array([3, 0, 3, 17])
    sub = model.take(state, index)
    for name, field in zip(AnalyticalState._fields, sub):
        np.testing.assert_array_equal(field, getattr(state, name)[index])
    arrays = model.state_to_arrays(state)
    assert set(arrays) == set(AnalyticalState._fields)
    restored = model.state_from_arrays(arrays)
    d_eps = np.full((state.l1.size, 2), [1e-5, -1e-5])
    full, _ = _drive(model, state, d_eps, 50)
    again, _ = _drive(model, restored, d_eps, 50)
    part, _ = _drive(model, sub, d_eps[index], 50)
    for a, b, c in zip(full, again, part):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a[index], c)  # a cell ignores the rest of its batch
    arrays["T1"][:] = 1.0  # the snapshot is a copy
    assert not np.any(state.T1 == 1.0)


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
