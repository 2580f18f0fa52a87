"""Generic database reading and the exact cell physics, checked against the DEM that wrote the data.

The small database is made in the test by the DEM (``tests/dem_database.py``): H-cells at
alpha0 = 55 deg, sampled along proportional legs, 40 % of the states perturbed.
"""

import h5py
import numpy as np
import pytest
import torch

from dem_database import build
from training import cell_physics
from training.dataset import active_pairs, DataError, load_database, split_by_path
from warp_hcell import generate as generate_command
from warp_hcell.core.parameters import DemSettings


@pytest.fixture(scope="module")
def db_file(tmp_path_factory):
    return build(tmp_path_factory.mktemp("db") / "small.h5", precompression=(0.0, 2e-3), n_directions=6,
                 spacing=1e-2, leg_length=0.1, probes_per_state=2, threads=1)


def _state(db, group="before"):
    with h5py.File(db, "r") as f:
        return {k: np.array(f[group][k]) for k in f[group]}


def test_loading_keeps_perturbed_and_mechanism_samples(db_file):
    db = load_database(db_file)
    with h5py.File(db_file, "r") as f:
        n = f.attrs["n_samples"]
        converged = np.array(f["converged"])
    assert db.n_samples == np.count_nonzero(converged) - db.n_jumps
    assert db.n_stored == n
    assert db.perturbed.any() and (~db.perturbed).any()
    assert db.mechanism.any()
    assert db.before["free_position"].shape == (db.n_samples, 4)
    assert db.schema.n_pairs == 15 and db.schema.n_free == 4


def test_contact_law_reproduces_the_dem_forces_and_equilibrium(db_file):
    """Normal forces of the stored DEM states, and ~zero unbalanced force after relaxation."""
    after = _state(db_file, "after")
    db = load_database(db_file)
    x = cell_physics.positions(db.schema, torch.tensor(after["cell_size"]), torch.tensor(after["free_position"]))
    c = cell_physics.contacts(db.schema, x)
    np.testing.assert_allclose(c.normal_force.numpy(), after["normal_force"], rtol=0, atol=1e-9 * after["normal_force"].max())
    force = cell_physics.pair_forces(c, torch.tensor(after["shear_force"]))
    residual = np.abs(cell_physics.unbalanced(db.schema, force, 6).numpy()).max(axis=1)
    scale = np.maximum(after["normal_force"].max(axis=1), 2e8 * 1e-9)
    assert np.all(residual <= 1.1 * DemSettings().force_tolerance * scale)  # the DEM's quasi-static tolerance


def test_advance_with_the_dem_displacement_reproduces_the_dem_increment(db_file):
    """Mid-increment tangent and Coulomb cap: shear forces and moment of small unperturbed probes."""
    db = load_database(db_file)
    after = _state(db_file, "after")
    with h5py.File(db_file, "r") as f:
        keep = np.array(f["converged"])
    m = np.linalg.norm(db.d_eps, axis=1)
    pick = np.flatnonzero(~db.perturbed & (m < 2e-5) & (m > 0))
    assert pick.size > 5
    state = [torch.from_numpy(db.before[k][pick]) for k in ("cell_size", "free_position", "shear_force")]
    d_free = torch.from_numpy(db.after_free_position[pick] - db.before["free_position"][pick])
    step = cell_physics.advance(db.schema, *state, torch.from_numpy(db.d_eps[pick]), d_free)
    truth = after["shear_force"][keep][pick]
    scale = after["normal_force"][keep][pick].max(axis=1, keepdims=True) + 1.0
    assert np.abs(step.shear_force.numpy() - truth).max() / scale.max() < 1e-3
    np.testing.assert_allclose(step.cell_size.numpy(), after["cell_size"][keep][pick], rtol=1e-14)


def test_split_is_by_whole_paths(db_file):
    db = load_database(db_file)
    split = split_by_path(db, val_fraction=0.2, test_fraction=0.2, seed=0)
    sets = [set(db.path_id[s]) for s in (split.train, split.val, split.test)]
    assert all(sets) and not (sets[0] & sets[1] or sets[0] & sets[2] or sets[1] & sets[2])
    assert sum(s.size for s in (split.train, split.val, split.test)) == db.n_samples
    assert active_pairs(db, split.train).sum() >= 6  # the H-cell's six contacts


def test_a_database_too_small_for_a_test_set_is_refused_before_training():
    """Three paths: the 10 % test set rounded to none and the training crashed at its end (an audit)."""
    from training.dataset import _held_out  # noqa: PLC0415

    rng = np.random.default_rng(0)
    with pytest.raises(DataError, match="3 paths are too few to split into training, validation and test"):
        _held_out(np.arange(3), 0.2, 0.1, rng, "db.h5")
    test, val = _held_out(np.arange(10), 0.2, 0.1, rng, "db.h5")
    assert test.size == 1 and val.size == 2


@pytest.mark.parametrize("case, message", [("missing", "no such database file"), ("text", "not a readable HDF5"),
                                           ("version1", "not the generic database")])
def test_bad_files_give_one_line_errors(tmp_path, case, message):
    path = tmp_path / "bad.h5"
    if case == "text":
        path.write_text("hello")
    elif case == "version1":
        with h5py.File(path, "w") as f:
            f.attrs.update({"format": "meso-hmodel-database", "format_version": 1})
    with pytest.raises(DataError, match=message) as info:
        load_database(path)
    assert "\n" not in str(info.value)


def test_the_generators_database_is_read(tmp_path):
    """The agreed format: a file written by ``python -m warp_hcell.generate`` loads and has both kinds of sample."""
    path = tmp_path / "gen.h5"
    assert generate_command.main(["--samples", "400", "--n-alpha0", "1", "--n-directions", "4", "--sample-spacing", "2e-2",
                                  "--threads", "1", "--out", str(path)]) in (0, None)
    db = load_database(path)
    assert db.n_samples == 400 and db.perturbed.any() and (~db.perturbed).any()
    assert db.schema.n_free == 4 and len(db.mesostructure_sha256) == 64


def test_a_rate_moved_by_round_off_only_is_degenerate_and_weighs_like_a_constant_one(db_file):
    """A free DOF held by symmetry (a fine grain on the cell axis) moves by round-off under the cell
    strain; its spread would weigh its errors by 1 / round-off^2 in the loss. Rates spread below
    RATE_STD_DEGENERATE of the largest get a standard deviation of 1, as an exactly constant one does."""
    from training.dataset import fit_normalisation, RATE_STD_DEGENERATE, tensors

    db = load_database(db_file)
    index = split_by_path(db, val_fraction=0.2, test_fraction=0.0, seed=0).train
    data = tensors(db, index, active_pairs(db, index))
    honest = fit_normalisation(db, data, index)
    assert honest.degenerate_rates == () and np.all(honest.rate_std < 1.0)  # the H-cell: no degenerate DOF

    rng = np.random.default_rng(0)
    target = data.target.clone()
    scale = db.schema.diameter * data.magnitude[:, 0]
    target[:, 1] = scale * torch.from_numpy(1e-5 * rng.standard_normal(target.shape[0]))  # round-off only
    target[:, 2] = 0.0                                                                       # exactly constant
    faked = fit_normalisation(db, type(data)(data.features, data.magnitude, data.unbalanced, target, data.scale), index)
    assert faked.degenerate_rates == (1,)
    assert faked.rate_std[1] == faked.rate_std[2] == 1.0
    np.testing.assert_array_equal(faked.rate_std[[0, 3]], honest.rate_std[[0, 3]])
    assert 1e-5 < RATE_STD_DEGENERATE * honest.rate_std.max()
