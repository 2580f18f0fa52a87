"""DEM backend: agreement with the analytical cell, protocol, determinism, batch invariance, equilibrium."""

import math
import warnings
from importlib import resources

import numpy as np
import pytest

from dem_oracle import NumpyIntegrator
from homogenization.backends import make_cell_model
from homogenization.backends.analytical import AnalyticalCell
from warp_hcell.dem.cell import DemCell
from warp_hcell.core.contract import CellModel
from warp_hcell.dem.integrator import MIN_CELLS_PER_CHUNK
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.dem.state import DemState

LAW = ContactLaw()
DATA = resources.files("warp_hcell") / "data"


def _h_cells(alpha0, dim=2):
    """One H-cell (r = 0.5 m) per opening angle [deg]: planar, or the ten-sphere cell for ``dim`` 3."""
    return [h_cell(a, 0.5) if dim == 2 else resolve_mesostructure(f"hcell3d:alpha0={float(a)!r}") for a in alpha0]


def _constant_volume_path(n_cells: int, theta: np.ndarray, iso: float, n_iso: int, delta: float, n_shear: int):
    """Local increments of an isotropic stage then a constant-volume stage d_eps11 = +delta = -d_eps22."""
    c2 = np.cos(2.0 * theta)
    yield from [np.full((n_cells, 2), iso / n_iso)] * n_iso
    yield from [np.stack([delta * c2, -delta * c2], axis=1)] * n_shear


def test_dem_matches_analytical_cell_along_constant_volume_path(device):
    """Low pressure, loose cell: closing cells slide, opening cells lose all contacts (spec section 10)."""
    theta = np.arange(8) * np.pi / 8
    n = theta.size
    dem, ana = DemCell(LAW, 0.5, device=device), AnalyticalCell(LAW, 0.5)
    sd, sa = dem.init_state(h_cell(55.0), n), ana.init_state(h_cell(55.0), n)
    worst = dict.fromkeys(("N1", "N2", "T1", "alpha_deg"), 0.0)
    force_max, slid, opened = 0.0, False, False
    for d_eps in _constant_volume_path(n, theta, 9e-4, 3, 2e-4, 80):
        sd, _ = dem.step(sd, d_eps)
        sa, _ = ana.step(sa, d_eps)
        od, oa = dem.observables(sd), ana.observables(sa)
        force_max = max(force_max, oa["N1"].max(), oa["N2"].max())
        worst = {k: max(v, np.abs(od[k] - oa[k]).max()) for k, v in worst.items()}
        slid |= bool(np.any((oa["N1"] > 0) & np.isclose(-oa["T1"], LAW.mu * oa["N1"], rtol=1e-9)))
        opened |= bool(np.any(~oa["closed1"] & ~oa["closed2"]))
        assert np.array_equal(od["closed1"], oa["closed1"]) and np.array_equal(od["closed2"], oa["closed2"])
    assert slid and opened and force_max > 1e5
    # docs/model.md section 10: 3-4 significant digits; measured 1.1e-4, 4.0e-4, 5.7e-4 of the
    # largest force and 1.5e-5 deg (docs/benchmarks.md "What CI checks")
    for name in ("N1", "N2", "T1"):
        assert worst[name] <= 1.5e-3 * force_max, (name, worst[name] / force_max)
    assert worst["alpha_deg"] <= 1e-4


@pytest.mark.parametrize("dim", (2, 3))
def test_dem_satisfies_the_cell_model_protocol_and_is_registered(dim):
    cell = make_cell_model("dem", contact_law=LAW, radius=0.5, dim=dim)
    assert isinstance(cell, DemCell) and isinstance(cell, CellModel) and cell.name == "dem"


def test_h_cell_observables_and_response(device):
    cell = DemCell(LAW, 0.5, device=device)
    alpha0 = np.array([40.0, 55.0, 70.0])
    state = cell.init_state(_h_cells(alpha0), 3)
    initial = cell.observables(state)
    np.testing.assert_allclose(initial["alpha_deg"], alpha0, rtol=1e-13)
    np.testing.assert_allclose(initial["d1"], 1.0, rtol=1e-14)
    assert np.all(initial["N1"] == 0.0) and np.all(initial["closed1"]) and np.all(initial["closed2"])
    new, response = cell.step(state, np.full((3, 2), 3e-4))
    obs = cell.observables(new)
    a = np.radians(obs["alpha_deg"])
    # Love-Weber in closed form (spec section 7) from the observed forces and branch lengths
    s_nn = 4 * obs["N1"] * obs["d1"] * np.cos(a) ** 2 + 4 * obs["T1"] * obs["d1"] * np.sin(a) * np.cos(a) \
        + 2 * obs["N2"] * obs["d2"]
    s_tt = 4 * obs["N1"] * obs["d1"] * np.sin(a) ** 2 - 4 * obs["T1"] * obs["d1"] * np.sin(a) * np.cos(a)
    np.testing.assert_allclose(response.moment[:, 0, 0], s_nn, rtol=1e-9)
    np.testing.assert_allclose(response.moment[:, 1, 1], s_tt, rtol=1e-9)
    np.testing.assert_allclose(response.moment[:, 0, 1], 0.0, atol=1e-9 * s_nn.max())
    assert np.all(s_nn > 0) and np.all(s_tt > 0)  # compression positive
    # equilibrium of grain 2 along n (spec section 5), to the force tolerance
    residual = obs["N2"] - obs["N1"] * np.cos(a) - obs["T1"] * np.sin(a)
    assert np.all(np.abs(residual) <= DemSettings().force_tolerance * np.maximum(obs["N1"], obs["N2"]))
    # V_cell = l2 (d2 + d1 cos a); l1, l2 follow the strain exactly
    np.testing.assert_allclose(response.area, obs["l2"] * (obs["d2"] + obs["d1"] * np.cos(a)), rtol=1e-12)
    np.testing.assert_allclose(obs["l1"], initial["l1"] * (1 - 3e-4), rtol=1e-15)
    np.testing.assert_allclose(obs["x_n1"], obs["l1"] / 2, rtol=1e-14)
    assert response.diagnostics["n_unconverged"] == 0 and np.all(obs["converged"])
    assert response.diagnostics["substeps"] == obs["substeps"].sum() >= 3 * math.ceil(3e-4 / DemSettings().refined_strain_per_substep)


def _history(cell, state, increments):
    for d_eps in increments:
        state, _ = cell.step(state, d_eps)
    return cell.state_to_arrays(state)


def _increments(rng, n_cells, n_steps=4):
    steps = [np.full((n_cells, 2), 3e-4)]
    steps += [rng.uniform(-1, 1, (n_cells, 2)) * 10 ** rng.uniform(-6, -3.5, (n_cells, 1)) for _ in range(n_steps)]
    return steps


def _assert_same(a, b, rows=slice(None)):
    for name in a:
        assert np.array_equal(a[name][rows], b[name]), name


def test_bitwise_determinism_and_batch_invariance(device):
    rng = np.random.default_rng(3)
    n = 2 * MIN_CELLS_PER_CHUNK + 37  # several CPU chunks with 2 and 3 threads
    alpha0 = rng.uniform(32.0, 85.0, n)
    increments = _increments(rng, n)
    cells = [DemCell(LAW, 0.5, device=device, threads=t) for t in (1, 2, 3, 1)]
    runs = [_history(cell, cell.init_state(_h_cells(alpha0), n), increments) for cell in cells]
    for other in runs[1:]:
        _assert_same(runs[0], other)
    # a cell alone, and the batch reversed, give the same cells bit for bit
    k = MIN_CELLS_PER_CHUNK + 3
    alone = _history(DemCell(LAW, 0.5, device=device), DemCell(LAW, 0.5, device=device).init_state(h_cell(alpha0[k]), 1),
                     [d[k:k + 1] for d in increments])
    _assert_same(runs[0], alone, rows=slice(k, k + 1))
    flipped = _history(DemCell(LAW, 0.5, device=device, threads=2),
                       DemCell(LAW, 0.5, device=device).init_state(_h_cells(alpha0[::-1]), n), [d[::-1] for d in increments])
    _assert_same(runs[0], flipped, rows=slice(None, None, -1))


@pytest.mark.parametrize("dim", (2, 3))
def test_step_is_pure_and_state_round_trips(device, dim):
    rng = np.random.default_rng(5)
    cell = DemCell(LAW, 0.5, device=device)
    state = cell.init_state(_h_cells(rng.uniform(46.0, 80.0, 5), dim), 5)
    state, _ = cell.step(state, np.full((5, dim), 2e-4))
    before = cell.state_to_arrays(state)
    d_eps = rng.uniform(-1e-4, 1e-4, (5, dim))
    first, r1 = cell.step(state, d_eps)
    _assert_same(before, cell.state_to_arrays(state))
    second, r2 = cell.step(cell.state_from_arrays(before), d_eps)
    _assert_same(cell.state_to_arrays(first), cell.state_to_arrays(second))
    assert np.array_equal(r1.moment, r2.moment) and np.array_equal(r1.area, r2.area)
    # take: gather with repetition, then step: same as stepping and gathering
    index = np.array([3, 0, 3])
    taken, _ = cell.step(cell.take(state, index), d_eps[index])
    _assert_same(cell.state_to_arrays(first), cell.state_to_arrays(taken), rows=index)


def test_a_fresh_backend_restores_any_mesostructure_from_its_arrays(device):
    """The arrays carry the topology: another DemCell rebuilds a fine-grain cell and steps it alike."""
    meso = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    cell = DemCell(LAW, 0.5, device=device)
    state, _ = cell.step(cell.init_state(meso, 3), np.full((3, 2), 3e-4))
    restored = DemCell(LAW, 0.5, device=device).state_from_arrays(cell.state_to_arrays(state))
    for name in ("pairs", "driven", "outer", "pair_label", "radius", "position", "cell_size"):
        assert np.array_equal(getattr(restored.model.meso, name), getattr(meso, name)), name
    d_eps = np.array([[1e-4, -1e-4], [0.0, 2e-4], [-1e-4, 0.0]])
    _assert_same(cell.state_to_arrays(cell.step(state, d_eps)[0]), cell.state_to_arrays(cell.step(restored, d_eps)[0]))


def test_the_backend_steps_as_the_numpy_oracle():
    rng = np.random.default_rng(11)
    alpha0 = rng.uniform(35.0, 80.0, 4)
    cell = DemCell(LAW, 0.5)
    state = cell.init_state(_h_cells(alpha0), 4)
    for d_eps in _increments(rng, 4, 2):
        new, _ = cell.step(state, d_eps)
        oracle = DemState.empty(4, 6, 15, "cpu")
        NumpyIntegrator(state.model).step(state.dem, oracle, d_eps)
        a, b = new.dem.to_numpy(), oracle.to_numpy()
        np.testing.assert_allclose(a["position"], b["position"], rtol=0, atol=1e-13)
        force_scale = np.abs(b["contact_force"]).max()
        np.testing.assert_allclose(a["contact_force"], b["contact_force"], rtol=0, atol=1e-9 * force_scale)
        state = new


def test_unequal_radii_free_dof_equilibrium_and_love_weber_vs_reactions(device):
    """Lateral grains 0.7 D: free DOFs balanced; S = sum_g F_g (x) x_g over the grains (boundary reactions)."""
    meso = load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")
    cell = DemCell(LAW, 0.5, device=device)
    n = 4
    state = cell.init_state(meso, n)
    increments = [np.full((n, 2), 2e-4)] * 2 + [np.array([[1e-4, -1e-4], [-1e-4, 1e-4], [2e-4, 0.0], [0.0, 5e-5]])] * 3
    for d_eps in increments:
        state, response = cell.step(state, d_eps)
    arrays = cell.state_to_arrays(state)
    f_i = arrays["contact_force"]  # on grain i of pair (i, j)
    grain_force = np.zeros_like(arrays["position"])
    for p, (i, j) in enumerate(meso.pairs):
        grain_force[:, i] += f_i[:, p]
        grain_force[:, j] -= f_i[:, p]
    force_max = np.linalg.norm(f_i, axis=-1).max()
    assert force_max > 1e4
    free = ~meso.driven
    assert np.abs(grain_force[:, free]).max() <= DemSettings().force_tolerance * force_max
    # the boundary exerts R_g = -F_g on driven DOFs; compression-positive S = sum_g F_g (x) x_g
    reactions_moment = np.einsum("cga,cgb->cab", grain_force, arrays["position"])
    np.testing.assert_allclose(response.moment, reactions_moment, rtol=0, atol=1e-6 * np.abs(reactions_moment).max())
    obs = cell.observables(state)
    assert {"N1", "N2", "T1", "alpha_deg", "x_n6", "x_t6"} <= set(obs)
    assert np.all(obs["N1"] > 0) and np.all(obs["converged"])


def test_fine_grain_file_runs_and_reports_every_grain(device):
    meso = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    cell = DemCell(LAW, 0.5, device=device)
    state, response = cell.step(cell.init_state(meso, 2), np.array([[4e-4, 4e-4], [-4e-4, -4e-4]]))
    obs = cell.observables(state)
    assert {f"x_n{i}" for i in range(1, 8)} <= set(obs)
    # compressed: 6 + 4 fine-grain contacts; extended: only 2-3 and 5-6 (free along n, unloaded, still touching)
    assert obs["n_contacts"].tolist() == [10, 2]
    assert obs["x_n7"][0] == 0.0 and obs["x_t7"][0] == 0.0  # stays at the centre by symmetry
    assert np.all(response.moment[1] == 0.0) and response.moment[0, 0, 0] > 0


def test_unconverged_cells_are_counted_and_warned():
    cell = DemCell(LAW, 0.5, settings=DemSettings(max_substeps=5))
    state = cell.init_state(h_cell(55.0), 2)
    with pytest.warns(RuntimeWarning, match="2 of 2 cells did not reach equilibrium within max_substeps = 5"):
        new, response = cell.step(state, np.full((2, 2), 1e-5))
    assert response.diagnostics["n_unconverged"] == 2
    assert not cell.observables(new)["converged"].any()


def test_bad_inputs_give_one_line_errors():
    cell = DemCell(LAW, 0.5)
    state = cell.init_state(h_cell(55.0), 2)
    with pytest.raises(ValueError, match=r"d_eps_local has shape \(3, 2\), expected \(2, 2\)"):
        cell.step(state, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="too large for max_substeps"):
        small = DemCell(LAW, 0.5, settings=DemSettings(max_substeps=1000))
        small.step(small.init_state(h_cell(55.0), 2), np.full((2, 2), 0.1))
    with pytest.raises(ValueError, match="has another topology than"):
        cell.init_state([h_cell(55.0), load_mesostructure(DATA / "h_cell_fine_grain.toml")], 2)
    with pytest.raises(ValueError, match=r"need one mesostructure or n_cells = 3 of them, got 2"):
        cell.init_state([h_cell(55.0)] * 2, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cell.step(state, np.zeros((2, 2)))


@pytest.mark.slow
@pytest.mark.parametrize("alpha0_deg, iso", [(55.0, 9e-4), (55.0, 0.026), (40.0, 0.0222)])
def test_dem_matches_analytical_to_three_digits_along_long_paths(alpha0_deg, iso):
    """36 orientations, constant volume to eps1 = 10 % (spec section 10: 3-4 significant digits)."""
    theta = np.arange(36) * np.pi / 36
    dem, ana = DemCell(LAW, 0.5), AnalyticalCell(LAW, 0.5)
    sd, sa = dem.init_state(h_cell(alpha0_deg), theta.size), ana.init_state(h_cell(alpha0_deg), theta.size)
    worst, force_max = dict.fromkeys(("N1", "N2", "T1", "alpha_deg"), 0.0), 0.0
    for d_eps in _constant_volume_path(theta.size, theta, iso, round(iso / 1e-4), 1e-4, 1000):
        (sd, _), (sa, _) = dem.step(sd, d_eps), ana.step(sa, d_eps)
        od, oa = dem.observables(sd), ana.observables(sa)
        force_max = max(force_max, oa["N1"].max(), oa["N2"].max())
        worst = {k: max(v, np.abs(od[k] - oa[k]).max()) for k, v in worst.items()}
    for name in ("N1", "N2", "T1"):
        assert worst[name] <= 1e-3 * force_max, name
    assert worst["alpha_deg"] <= 1e-3
