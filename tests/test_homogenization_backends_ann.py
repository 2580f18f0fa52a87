"""Generic ANN backend: protocol, contact-law diagnostics, autograd tangent, mesostructure checks, shipped model.

Protocol tests use networks trained for a few epochs on small DEM databases made in the test
(``tests/dem_database.py``); the physics test uses the shipped default model.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from dem_database import build
from homogenization.cli import biaxial
from homogenization.element_test import driver, programme as programmes
from homogenization.backends import make_cell_model
from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell
from training.checkpoint import CheckpointError
from training.train import main as train_main
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.core.parameters import ContactLaw

LAW, RADIUS = ContactLaw(), 0.5
DATA = Path(__file__).resolve().parents[1] / "warp_hcell" / "data"
LATERAL = DATA / "h_cell_lateral_0.7D.toml"


def _train(folder: Path, mesostructure=None, alpha0_deg=(55.0,)) -> Path:
    db = build(folder / "db.h5", mesostructure=mesostructure, alpha0_deg=alpha0_deg, precompression=(0.0, 3e-3),
               n_directions=6, spacing=1e-2, leg_length=0.1, probes_per_state=2, threads=1)
    assert train_main(["--data", str(db), "--out", str(folder / "m.pt"), "--epochs", "20", "--hidden", "16,16",
                       "--threads", "1", "--no-rollout"]) == 0
    return folder / "m.pt"


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    return _train(tmp_path_factory.mktemp("hcell"))


@pytest.fixture(scope="module")
def two_start_model(tmp_path_factory):
    """An H-cell model whose database started from alpha0 = 40 and 55 deg."""
    return _train(tmp_path_factory.mktemp("hcell2"), alpha0_deg=(40.0, 55.0))


@pytest.fixture(scope="module")
def lateral_model(tmp_path_factory):
    return _train(tmp_path_factory.mktemp("lateral"), load_mesostructure(LATERAL))


@pytest.fixture(scope="module")
def cell(model_path):
    return AnnCell(LAW, RADIUS, model=model_path)


def _loaded(cell, n=8, seed=0):
    """A compressed state after a few increments, and the next increments, shape (n, 2)."""
    rng = np.random.default_rng(seed)
    state = cell.init_state(h_cell(55.0), n)
    for _ in range(10):
        state, _ = cell.step(state, np.full((n, 2), 2e-4))
    return state, rng.normal(scale=1e-5, size=(n, 2))


def test_initial_state_is_the_touching_force_free_cell_of_the_dem(two_start_model):
    cell = AnnCell(LAW, RADIUS, model=two_start_model)
    cells = [h_cell(40.0), h_cell(55.0)]
    state = cell.init_state(cells, 2)
    response = cell.response(state)
    dem = DemCell(LAW, RADIUS)
    reference = dem.response(dem.init_state(cells, 2))
    assert np.abs(response.moment).max() < 1e-6
    np.testing.assert_allclose(response.area, reference.area, rtol=1e-14)
    obs = cell.observables(state)
    np.testing.assert_allclose(obs["alpha_deg"], [40.0, 55.0], rtol=1e-12)
    assert {"l1", "l2", "S_nn", "S_tt", "area", "N1", "N2", "T1", "x_n2"} <= set(obs)


def test_step_is_pure_and_batch_invariant_and_round_trips(cell):
    state, d = _loaded(cell)
    before = cell.state_to_arrays(state)
    new, response = cell.step(state, d)
    for key, value in cell.state_to_arrays(state).items():
        assert np.array_equal(value, before[key])
    alone, single = cell.step(cell.take(state, np.array([3])), d[3:4])
    np.testing.assert_allclose(single.moment[0], response.moment[3], rtol=1e-12, atol=1e-9)
    again = cell.state_from_arrays(cell.state_to_arrays(new))
    assert all(np.array_equal(a, b) for a, b in zip(again, new))
    assert response.moment.shape == (8, 2, 2) and response.area.shape == (8,)


def test_diagnostics_count_the_contact_law_branches(cell):
    state, _ = _loaded(cell)
    _, response = cell.step(state, np.tile([[-3e-3, -3e-3]], (8, 1)))  # strong extension opens contacts
    ood_counts = {"n_ood", "n_ood_checked"} if cell.ood is not None else set()  # with an index (training.ood)
    assert set(response.diagnostics) == {"n_coulomb_capped", "n_tension_clipped", "n_mechanism", "n_relaxation_scaled",
                                       "n_grains_held"} | ood_counts
    assert response.diagnostics["n_tension_clipped"] == 8 and response.diagnostics["n_relaxation_scaled"] == 0


def test_a_zero_increment_is_a_no_op(cell):
    """Stress control brackets the increment from zero: the state must not move at zero.

    Nor may the stress: the zero step reports, bit for bit, the moment of the step that made
    the state, and the moment of ``response`` (torch path; to rounding).
    """
    state, d = _loaded(cell)
    state, last = cell.step(state, d)
    new, response = cell.step(state, np.zeros((8, 2)))
    assert all(np.array_equal(a, b) for a, b in zip(new, state))
    np.testing.assert_array_equal(response.moment, last.moment)
    np.testing.assert_allclose(response.moment, cell.response(state).moment, rtol=0,
                               atol=1e-12 * np.abs(last.moment).max())
    assert response.diagnostics["n_relaxation_scaled"] == 8


def test_tangent_matches_central_finite_differences(cell):
    """The tangent of ``step`` against central differences of the float64 increment.

    ``step`` runs a float32 network, equal to ``MesoNet.advance`` to ~1e-7
    (``tests/test_training_inference.py``, which also checks its forward-mode tangent against
    autograd); that rounding, divided by h = 1e-8, would be ~3e-4 of the tangent, so the
    differences are taken on ``MesoNet.advance``.
    """
    state, d = _loaded(cell)
    _, response = cell.step(state, d, with_tangent=True)
    tensors = [torch.from_numpy(np.asarray(a)) for a in state]
    h = 1e-8
    fd = np.zeros((8, 2, 2))
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        with torch.inference_mode():
            plus = cell.net.advance(*tensors, torch.from_numpy(d + e)).moment.numpy()
            minus = cell.net.advance(*tensors, torch.from_numpy(d - e)).moment.numpy()
        fd[:, :, j] = (plus - minus)[:, [0, 1], [0, 1]] / (2 * h)
    scale = np.abs(fd).max()
    assert scale > 1e6
    np.testing.assert_allclose(response.tangent, fd, rtol=0, atol=1e-4 * scale)
    assert cell.step(state, d)[1].tangent is None
    assert cell.step(state, d)[1].diagnostics == response.diagnostics


def test_a_model_of_another_mesostructure_is_refused(model_path, two_start_model, lateral_model, tmp_path, capsys):
    with pytest.raises(CheckpointError, match="has another learning state") as info:
        AnnCell(LAW, RADIUS, model=model_path).init_state(load_mesostructure(LATERAL), 2)
    assert "\n" not in str(info.value)
    lateral = AnnCell(LAW, RADIUS, model=lateral_model)
    assert lateral.response(lateral.init_state(load_mesostructure(LATERAL), 2)).moment.shape == (2, 2, 2)
    with pytest.raises(CheckpointError, match="has another learning state"):
        lateral.init_state(h_cell(55.0), 2)
    with pytest.raises(CheckpointError, match="starts outside the range"):  # H-cells beyond the database's starts
        AnnCell(LAW, RADIUS, model=two_start_model).init_state(h_cell(60.0), 2)
    with pytest.raises(CheckpointError, match="starts outside the range"):
        AnnCell(LAW, RADIUS, model=model_path).init_state(h_cell(47.5), 2)  # started from 55 only
    AnnCell(LAW, RADIUS, model=two_start_model).init_state(h_cell(47.5), 2)  # between 40 and 55: accepted
    with pytest.raises(CheckpointError, match="another learning state"):  # one cell of another mesostructure in the batch
        lateral.init_state([load_mesostructure(LATERAL), resolve_mesostructure("hcell-unequal:lateral=0.6")], 2)
    common = ["--p0", "1e5", "--eps-max", "0.001", "--increment", "1e-4", "--orientations", "4"]
    for argv in (["--backend", "ann", "--model", str(lateral_model)],
                 ["--backend", "dem,ann", "--model", str(model_path), "--mesostructure", str(LATERAL)]):
        capsys.readouterr()
        code = biaxial.run_main(biaxial.main, argv + common + ["--out", str(tmp_path / "run")])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "ann: " in err, err
        assert not (tmp_path / "run").exists()  # refused before any backend ran


def test_inference_runs_on_one_torch_thread_by_default(model_path):
    AnnCell(LAW, RADIUS, model=model_path)
    assert torch.get_num_threads() == 1


@pytest.mark.skipif(not default_model_path().is_file(), reason="default model not installed")
def test_shipped_model_follows_the_analytical_cell_in_a_short_constant_volume_test():
    programme = programmes.biaxial(5.85e6, 0.02, 1e-4, iso_increment=1e-4)
    runs = {name: driver.run(make_cell_model(name), programme, mesostructure=h_cell(55.0), n_orientations=12, progress=False)
            for name in ("analytical", "ann")}
    a, b = runs["analytical"], runs["ann"]
    assert a.p.shape == b.p.shape
    assert np.abs(b.p - a.p).max() <= 1.5e-5 * 5.85e6  # measured 3e-6 / 7e-6 (docs/benchmarks.md "What CI checks")
    assert np.abs(b.q - a.q).max() <= 3.5e-5 * 5.85e6


@pytest.mark.skipif(not default_model_path().is_file(), reason="default model not installed")
@pytest.mark.parametrize("p0, p_tolerance, q_tolerance", [(2e5, 0.0035, 0.01), (3e5, 0.01, 0.02)])
def test_shipped_model_follows_the_analytical_cell_through_a_constant_volume_reversal(p0, p_tolerance, q_tolerance):
    """+5 % then -5 % at constant volume, increments 1e-4 (the test the model missed by 7 % of p0
    before the active-learning rounds of `make reproduce`; p0 = 3e5 is a pressure the rounds never
    probed). Measured with 24 cells: 0.07 / 0.21 % (2e5), 0.32 / 0.55 % (3e5) of p0 (2026-12-07, the 2 x 24 model),
    checked within 5x; the DEM follows the analytical cell here to 0.02 % of p0."""
    n = programmes.n_increments_for(0.05, 1e-4)
    programme = (programmes.isotropic(p0, increment=1e-4), programmes.constant_volume_biaxial(0.05, n, label="shear"),
                 programmes.constant_volume_biaxial(-0.1, 2 * n, label="reverse"))
    runs = {name: driver.run(make_cell_model(name), programme, mesostructure=h_cell(55.0), n_orientations=24,
                             progress=False) for name in ("analytical", "ann")}
    shear = {name: r.stage != r.stage[0] for name, r in runs.items()}
    p = {name: r.p[shear[name]] for name, r in runs.items()}
    q = {name: r.q[shear[name]] for name, r in runs.items()}
    assert p["ann"].size == p["analytical"].size == 3 * n
    assert np.abs(p["ann"] - p["analytical"]).max() <= p_tolerance * p0
    assert np.abs(q["ann"] - q["analytical"]).max() <= q_tolerance * p0
    assert np.ptp(q["analytical"]) > 0.5 * p0  # the reversal swings q through the test
