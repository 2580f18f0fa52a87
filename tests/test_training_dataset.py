"""Database loading (one-line errors), sample selection, split by path, normalisation.

Format-only tests: the fixture writes a conforming file of random numbers (the physics
does not matter here; training on a real generated database is in test_training_train.py).
"""

import math

import h5py
import numpy as np
import pytest
import torch

from training.dataset import DataError, fit_normalisation, load_database, split_by_path, tensors
from warp_hcell.database import FORMAT, INPUT_FEATURES, OUTPUT_FEATURES, STATE_FEATURES

KN, RADIUS = 2e8, 0.5
ALPHA0 = (30.0, 40.0, 55.0, 70.0, 89.0)
PATHS_PER_ALPHA0, SAMPLES_PER_PATH = 10, 6


def _write(path, *, n_bad=0, attrs=None, drop=None, outputs_rows=None):
    """Random conforming database: 5 alpha0 x 10 paths x 6 samples; the first n_bad samples bad."""
    rng = np.random.default_rng(0)
    n = len(ALPHA0) * PATHS_PER_ALPHA0 * SAMPLES_PER_PATH
    path_id = np.repeat(np.arange(len(ALPHA0) * PATHS_PER_ALPHA0), SAMPLES_PER_PATH)
    alpha0 = np.repeat(ALPHA0, PATHS_PER_ALPHA0 * SAMPLES_PER_PATH)
    state = np.column_stack([rng.uniform(40, 80, n), rng.uniform(0, 1e6, (n, 2)), rng.uniform(-1e5, 1e5, n),
                             rng.uniform(1.5, 2.0, n), rng.uniform(1.0, 1.7, n)])
    inputs = np.column_stack([rng.normal(scale=1e-5, size=(n, 2)), state])
    magnitude = np.hypot(inputs[:, 0], inputs[:, 1])[:, None]
    outputs = state[:, :4] + magnitude * np.clip(rng.normal(size=(n, 4)), -3, 3) * [30.0, 1e8, 1e8, 1e8]
    table = np.zeros((n, len(STATE_FEATURES)))
    table[:, STATE_FEATURES.index("alpha_deg")] = 60.0
    table[:, STATE_FEATURES.index("closed1")] = 1.0
    valid = np.ones(n, bool)
    converged = np.ones(n, bool)
    if n_bad:
        valid[0] = False
        converged[1] = False
        inputs[2, 3] = np.nan
        inputs[3, :2] = 0.0
    data = {"inputs": inputs, "outputs": outputs if outputs_rows is None else outputs[:outputs_rows],
            "pre_state": table, "post_state": table, "path_id": path_id, "probe_id": np.zeros(n, np.int64),
            "alpha0_deg": alpha0, "converged": converged, "valid": valid}
    root = {"format": FORMAT, "format_version": 1, "kn": KN, "kt": 0.5 * KN, "phi_g_deg": 30.0, "radius": RADIUS,
            **(attrs or {})}
    with h5py.File(path, "w") as f:
        for key, value in root.items():
            f.attrs[key] = value
        for name, value in data.items():
            if name != drop:
                dset = f.create_dataset(name, data=value)
                if name in ("inputs", "outputs"):
                    dset.attrs["feature_names"] = list(INPUT_FEATURES if name == "inputs" else OUTPUT_FEATURES)
    return path


@pytest.fixture
def db_file(tmp_path):
    return _write(tmp_path / "db.h5", n_bad=4)


def test_selection_keeps_valid_converged_finite_nonzero_probes(db_file):
    db = load_database(db_file)
    assert db.n_stored == 300 and db.n_samples == 296
    assert db.inputs.shape == (296, 8) and db.outputs.shape == (296, 4)
    assert (db.kn, db.radius, db.diameter, db.kt_over_kn, db.phi_g_deg) == (KN, RADIUS, 1.0, 0.5, 30.0)
    assert len(db.sha256) == 64


@pytest.mark.parametrize("case, message", [
    ("missing", "no such database file"),
    ("garbage", "not a readable HDF5 file"),
    ("format", "format attribute is 'something-else'"),
    ("version", "format_version 7 is not supported"),
    ("no_kn", "root attribute 'kn' missing"),
    ("no_outputs", "dataset 'outputs' missing"),
    ("short_outputs", "dataset 'outputs' has 10 samples, inputs has 300"),
])
def test_bad_files_give_one_line_errors(tmp_path, case, message):
    path = tmp_path / "db.h5"
    if case == "garbage":
        path.write_bytes(b"this is not HDF5\n" * 10)
    elif case == "format":
        _write(path, attrs={"format": "something-else"})
    elif case == "version":
        _write(path, attrs={"format_version": 7})
    elif case == "no_kn":
        _write(path)
        with h5py.File(path, "a") as f:
            del f.attrs["kn"]
    elif case == "no_outputs":
        _write(path, drop="outputs")
    elif case == "short_outputs":
        _write(path, outputs_rows=10)
    with pytest.raises(DataError) as info:
        load_database(path)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_split_is_by_whole_paths_and_holds_out_alpha0_values(db_file):
    db = load_database(db_file)
    split = split_by_path(db, val_fraction=0.2, test_path_fraction=0.1, n_test_alpha0=1, seed=3)
    sets = [set(db.path_id[i]) for i in (split.train, split.val, split.test)]
    assert not (sets[0] & sets[1]) and not (sets[0] & sets[2]) and not (sets[1] & sets[2])
    assert split.train.size + split.val.size + split.test.size == db.n_samples
    (held,) = split.test_alpha0_deg
    assert held in ALPHA0[1:-1]  # never an extreme value (no extrapolation)
    assert np.all(np.isin(np.flatnonzero(db.alpha0_deg == held), split.test))
    assert held not in db.alpha0_deg[split.train] and held not in db.alpha0_deg[split.val]
    # 40 remaining paths: 4 to test, then 36 -> 7 validation + 29 training
    assert (len(sets[2]), len(sets[1]), len(sets[0])) == (14, 7, 29)
    again = split_by_path(db, val_fraction=0.2, test_path_fraction=0.1, n_test_alpha0=1, seed=3)
    assert all(np.array_equal(getattr(split, k), getattr(again, k)) for k in ("train", "val", "test"))
    other = split_by_path(db, val_fraction=0.2, test_path_fraction=0.1, n_test_alpha0=1, seed=4)
    assert not np.array_equal(other.train, split.train)


def test_normalisation_uses_training_statistics_and_spec_units(db_file):
    db = load_database(db_file)
    split = split_by_path(db, val_fraction=0.2, test_path_fraction=0.1, n_test_alpha0=1, seed=0)
    norm = fit_normalisation(db, split.train)
    x, y = tensors(db, split.train, norm)
    assert torch.allclose(x.mean(0), torch.zeros(12, dtype=torch.float64), atol=1e-12)
    # every random force is > 0: the contact flags are constant, z-scored with std 1 to 0
    constant = torch.tensor([False] * 8 + [True, True, False, False])
    expected_std = torch.where(constant, 0.0, 1.0).to(torch.float64)
    assert torch.allclose(x.std(0, unbiased=False), expected_std, atol=1e-12)
    assert np.array_equal(norm.feature_std[8:10], [1.0, 1.0])
    assert torch.allclose(y.mean(0), torch.zeros(4, dtype=torch.float64), atol=1e-12)
    # one sample by hand: rate = increment / |d_eps|, alpha in rad, forces in kn D
    i = split.val[0]
    magnitude = math.hypot(*db.inputs[i, :2])
    expected = (db.outputs[i] - db.inputs[i, 2:6]) / magnitude
    expected[0] = math.radians(expected[0])
    expected[1:] /= KN * 2 * RADIUS
    _, y_val = tensors(db, split.val[:1], norm)
    assert np.allclose(y_val[0].numpy() * norm.rate_std + norm.rate_mean, expected, rtol=1e-12)
    assert np.isclose(norm.feature_mean[6], np.mean(db.inputs[split.train, 6]) / (2 * RADIUS))


def test_too_few_paths_is_a_one_line_error(tmp_path):
    path = _write(tmp_path / "db.h5")
    with h5py.File(path, "a") as f:
        f["path_id"][...] = 0
    with pytest.raises(DataError, match="too few to split"):
        split_by_path(load_database(path), val_fraction=0.2, test_path_fraction=0.0, n_test_alpha0=0, seed=0)


def test_snap_through_jumps_are_dropped_and_counted(tmp_path):
    path = _write(tmp_path / "db.h5")
    with h5py.File(path, "a") as f:
        inputs, outputs = f["inputs"][()], f["outputs"][()]
        magnitude = math.hypot(*inputs[5, :2])
        outputs[5, 0] = inputs[5, 2] + math.degrees(11.0 * magnitude)  # rate 11 rad per unit strain
        outputs[6, 1] = inputs[6, 3] + 9.0 * math.hypot(*inputs[6, :2]) * KN * 2 * RADIUS  # rate 9 kn D: kept
        f["outputs"][...] = outputs
    db = load_database(path)
    assert db.n_jumps == 1 and db.n_samples == 299
    assert not np.any(np.all(db.inputs == inputs[5], axis=1))
