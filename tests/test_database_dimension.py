"""The learning database and the meso-ANN take the dimension of the cell from the cell.

The 2D digests below were computed with the code at main before the database, the training
and the ANN backend learnt the spatial cell (commit e8c08f1): a tiny 2D database of a fixed
seed and a few epochs of training on it must stay bit for bit what they were.
"""

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from warp_hcell.database import exploration, format as database, generate, probing
from warp_hcell.database.learning_state import evaluate, free_coordinates
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.builders import mesostructure_arg
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.hcell import StartCells, h_cell
from warp_hcell.core.parameters import ContactLaw, DatabaseSettings, DemSettings

DATA = Path(__file__).resolve().parents[1] / "warp_hcell" / "data"
TINY = DatabaseSettings(samples=300, chunk_size=150, precompression=(0.0, 1e-3), n_directions=6,
                        sample_spacing=1e-2, leg_length=0.03, leg_volumetric=0.05, leg_refinement=1)
H_CELL_DIGEST = "6533de518fdcfa63e117be74a336fb40b4304fda64d0badbfdad65e534ef2c28"
"""sha256 of the arrays of the H-cell database of ``_h_cell_database`` at main (54 datasets)."""
FINE_DIGEST = "efd43f5feb2fee41fcb9e5f7644683f431bb441e786c5db5bdadcbdba247786d"
"""The same for the cell with a fine grain (``h_cell_fine_grain.toml``)."""
WEIGHTS_DIGEST = "bdf459aa0295c7df733fa81911f4a79ac2046ed4782987a9a554476b7c0f9344"
"""sha256 of the state_dict after ``_tiny_fit`` on the H-cell database at main."""


@pytest.fixture(autouse=True)
def fixed_revision(monkeypatch):
    monkeypatch.setattr(generate, "provenance", lambda: {"git_revision": "pinned"})


def array_digest(data: dict) -> str:
    """sha256 over the names, dtypes, shapes and bytes of ``data``'s arrays, in name order."""
    h = hashlib.sha256()
    for name in sorted(data):
        a = np.ascontiguousarray(data[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _h_cell_database(out: Path) -> Path:
    starts = StartCells(n_alpha0=1, alpha0_focus_deg=(55.0,)).build()
    generate.generate(h_cell(), TINY, out, seed=5, starts=starts, threads=1)
    return out


def test_2d_databases_unchanged(tmp_path):
    data, _ = database.read_database(_h_cell_database(tmp_path / "h.h5"))
    assert len(data) == 54
    assert array_digest(data) == H_CELL_DIGEST
    fine = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    generate.generate(fine, TINY, tmp_path / "fine.h5", seed=5, threads=1)
    assert array_digest(database.read_database(tmp_path / "fine.h5")[0]) == FINE_DIGEST


def test_2d_training_unchanged(tmp_path):
    from training.dataset import load_database
    from training.train import TrainConfig, fit

    db = load_database(_h_cell_database(tmp_path / "h.h5"))
    net = fit(db, TrainConfig(hidden=(6,), epochs=3, batch_size=64, seed=2, rollout=False)).net
    h = hashlib.sha256()
    for name, value in net.state_dict().items():
        h.update(name.encode())
        h.update(value.detach().cpu().numpy().tobytes())
    assert h.hexdigest() == WEIGHTS_DIGEST


SPATIAL = mesostructure_arg("hcell3d:alpha0=55").build()
TINY_3D = DatabaseSettings(samples=400, chunk_size=200, precompression=(0.0, 1e-3), n_directions=12,
                           sample_spacing=1e-2, leg_length=0.03, leg_volumetric=0.05, leg_refinement=1)


@pytest.fixture(scope="module")
def spatial_db(tmp_path_factory):
    """A tiny database of the ten-sphere H-cell (hcell3d, alpha0 = 55 deg)."""
    out = tmp_path_factory.mktemp("h3") / "h3.h5"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(generate, "provenance", lambda: {"git_revision": "pinned"})
        generate.generate(SPATIAL, TINY_3D, out, seed=4, threads=1)
    return database.read_database(out)


def test_spatial_leg_directions_are_unit_and_spread():
    directions = exploration.leg_directions(TINY_3D, 3)
    assert directions.shape == (12, 3)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=1e-14)
    # nearly even on the sphere: every direction has a neighbour within 75 deg, none closer than 40 deg
    cosines = directions @ directions.T - 2.0 * np.eye(12)
    nearest = np.degrees(np.arccos(cosines.max(axis=1)))
    assert nearest.max() < 75.0 and nearest.min() > 40.0
    assert abs(directions.mean(axis=0)).max() < 0.05


def test_spatial_turns_keep_their_angle():
    directions = exploration.leg_directions(TINY_3D, 3)
    steps, angle, plane = exploration.turn_draws(replace(TINY_3D, reversal_legs=2), 0, 2, 3)
    assert plane.shape == (2, 12, 2, 3) and steps.shape == angle.shape == (2, 12, 2)
    leg = np.tile(directions, (4, 1))
    turn = angle.transpose(0, 2, 1).reshape(-1)
    out = exploration.turned(leg, turn, plane.transpose(0, 2, 1, 3).reshape(-1, 3))
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-13)
    np.testing.assert_allclose(np.arccos(np.clip(np.sum(out * leg, axis=1), -1, 1)), np.abs(turn), atol=1e-7)
    planar_steps, planar_angle, none = exploration.turn_draws(replace(TINY_3D, reversal_legs=2), 0, 2, 2)
    assert none is None
    np.testing.assert_array_equal(planar_angle, angle)  # the planar draws come first
    np.testing.assert_array_equal(planar_steps, steps)


def test_spatial_probes_are_isotropic():
    d_eps = probing.probe_increments(TINY_3D, 1, 0, 20000, 3)
    magnitude = np.linalg.norm(d_eps, axis=1)
    assert TINY_3D.probe_min * (1 - 1e-12) <= magnitude.min() and magnitude.max() <= TINY_3D.probe_max * (1 + 1e-12)
    unit = d_eps / magnitude[:, None]
    assert abs(unit.mean(axis=0)).max() < 0.03
    np.testing.assert_allclose((unit**2).mean(axis=0), 1.0 / 3.0, atol=0.02)


def test_spatial_database_layout(spatial_db):
    data, attrs = spatial_db
    n = TINY_3D.samples
    assert data["d_eps"].shape == (n, 3) and data["before/cell_size"].shape == (n, 3)
    assert data["before/shear_force"].shape == (n, SPATIAL.n_pairs, 3)
    assert data["after/moment"].shape == (n, 9)
    assert data["states/eps"].shape[1] == 3
    assert attrs["n_unconverged"] == 0
    # legs left the isotropic axis in every direction of the Fibonacci set
    legs = np.isfinite(data["states/direction_deg"])
    assert np.unique(data["states/direction_deg"][legs]).size == TINY_3D.n_directions


def test_spatial_samples_recheck_against_the_dem(spatial_db):
    """The stored 3D before-state, the probe and the schema give the stored after-state exactly."""
    data, _ = spatial_db
    schema = SPATIAL.schema()
    law, tol = ContactLaw(), DemSettings().contact_tolerance
    rows = np.concatenate([np.array([0, 17, 233, 399]), np.flatnonzero(data["perturbed"])[:3]])
    context = probing.ProbeContext(DemCell(law, 0.5, threads=1), SPATIAL, schema, {}, law, tol)
    before = evaluate(schema, data["before/cell_size"][rows], data["before/free_position"][rows],
                      data["before/shear_force"][rows], law, tol)
    np.testing.assert_array_equal(before["normal_force"], data["before/normal_force"][rows])
    np.testing.assert_array_equal(before["unbalanced"], data["before/unbalanced"][rows])
    cell = context.cell_model
    new, response = cell.step(cell.state_from_arrays(probing.canonical_dem_arrays(
        context, before, data["before/cell_size"][rows])), data["d_eps"][rows])
    arrays = cell.state_to_arrays(new)
    np.testing.assert_array_equal(free_coordinates(schema, arrays["position"]), data["after/free_position"][rows])
    np.testing.assert_array_equal(arrays["cell_size"], data["after/cell_size"][rows])
    np.testing.assert_allclose(data["after/moment"][rows].reshape(-1, 3, 3), response.moment, rtol=1e-9,
                               atol=1e-6 * np.abs(response.moment).max())
    np.testing.assert_array_equal(data["after/contact"][rows], arrays["contact"])
    # the learning state's forces are the DEM's own on a DEM state (unperturbed rows)
    plain = ~data["perturbed"][rows]
    np.testing.assert_allclose(data["after/unbalanced"][rows][plain], 0.0,
                               atol=1e-6 * data["after/normal_force"][rows].max())


def test_spatial_cli(tmp_path):
    out = tmp_path / "x.h5"
    code = generate.main(["--mesostructure", "hcell3d:alpha0=55", "--samples", "60", "--chunk-size", "30",
                          "--precompression", "0", "1e-3", "--n-directions", "6", "--sample-spacing", "1e-2",
                          "--threads", "1", "--out", str(out), "--quiet"])
    assert code == 0
    data, attrs = database.read_database(out)
    assert data["d_eps"].shape == (60, 3) and attrs["n_samples"] == 60
