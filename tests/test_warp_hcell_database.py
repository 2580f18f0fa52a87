"""Tests of warp_hcell.database: column mapping, units, byte-stable writing, reading, errors."""

import h5py
import numpy as np
import pytest

from warp_hcell import database


def fake_samples(n=5, seed=0):
    rng = np.random.default_rng(seed)
    pre, post = rng.random((n, 13)), rng.random((n, 13))
    samples = database.sample_arrays(rng.random((n, 2)), pre, post)
    samples.update(path_id=np.arange(n), probe_id=np.zeros(n, np.int64), alpha0_deg=np.full(n, 55.0),
                   state_index=np.arange(n), converged=np.ones(n, bool), valid=np.ones(n, bool))
    states = {"observables": pre, "path_id": np.arange(n), "backend/position": rng.random((n, 6, 2))}
    return samples, states


def test_state_table_columns_and_flags():
    n = 3
    observables = {name: np.full(n, float(i)) for i, name in enumerate(database.STATE_FEATURES)}
    observables["closed1"] = np.array([True, False, True])
    observables["extra"] = np.zeros(n)
    table = database.state_table(observables)
    assert table.shape == (n, 13) and table.dtype == np.float64
    np.testing.assert_array_equal(table[:, 0], 0.0)
    np.testing.assert_array_equal(table[:, database.STATE_FEATURES.index("closed1")], [1.0, 0.0, 1.0])


def test_sample_arrays_take_pre_inputs_and_post_outputs():
    samples, _ = fake_samples()
    col = {name: i for i, name in enumerate(database.STATE_FEATURES)}
    np.testing.assert_array_equal(samples["inputs"][:, 2], samples["pre_state"][:, col["alpha_deg"]])
    np.testing.assert_array_equal(samples["inputs"][:, 7], samples["pre_state"][:, col["l2"]])
    np.testing.assert_array_equal(samples["outputs"][:, 3], samples["post_state"][:, col["T1"]])
    assert database.INPUT_FEATURES[:2] == ("d_eps_n", "d_eps_t")


def test_round_trip_attrs_and_units(tmp_path):
    samples, states = fake_samples()
    attrs = {"format": database.FORMAT, "format_version": database.FORMAT_VERSION, "seed": 7,
             "generator": {"samples": 5}}
    database.write_database(tmp_path / "a.h5", samples, states, attrs)
    read, read_states, read_attrs = database.read_database(tmp_path / "a.h5")
    for name in database.SAMPLE_DATASETS:
        np.testing.assert_array_equal(read[name], samples[name])
    np.testing.assert_array_equal(read_states["backend/position"], states["backend/position"])
    assert read_attrs["seed"] == 7 and read_attrs["generator"] == '{"samples": 5}'
    with h5py.File(tmp_path / "a.h5") as f:
        assert list(f["inputs"].attrs["feature_names"]) == list(database.INPUT_FEATURES)
        assert list(f["inputs"].attrs["units"]) == ["-", "-", "deg", "N", "N", "N", "m", "m"]
        assert list(f["outputs"].attrs["units"]) == ["deg", "N", "N", "N"]
        assert f["alpha0_deg"].attrs["units"] == "deg" and f["valid"].attrs["description"]
    # no timestamps: the same content gives the same bytes
    database.write_database(tmp_path / "b.h5", samples, states, attrs)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()


def test_read_rejects_other_files(tmp_path):
    samples, states = fake_samples()
    database.write_database(tmp_path / "old.h5", samples, states, {"format": database.FORMAT, "format_version": 0})
    with pytest.raises(ValueError, match="is not a meso-hmodel-database file of format_version 1"):
        database.read_database(tmp_path / "old.h5")
