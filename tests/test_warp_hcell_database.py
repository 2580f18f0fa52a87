"""Tests of warp_hcell.database.format (format version 2): schema datasets, attrs, byte-stable writing,
reading, version and hash checks."""

import json

import h5py
import numpy as np
import pytest

from warp_hcell.database import format as database
from warp_hcell.mesostructures.files import describe, description_sha256, from_description
from warp_hcell.mesostructures.hcell import h_cell


def fake_database(n=5, seed=0):
    meso = h_cell()
    schema = meso.schema()
    rng = np.random.default_rng(seed)
    data = database.schema_datasets(schema)
    for group in database.STATE_GROUPS:
        for name, feature in schema.features.items():
            data[f"{group}/{name}"] = rng.random((n, len(feature.names)))
    data.update(d_eps=rng.random((n, 2)), mechanism=np.zeros(n, bool), perturbed=np.ones(n, bool),
                converged=np.ones(n, bool), state_id=np.arange(n), path_id=np.arange(n), substeps=np.arange(n),
                valid=np.ones(n, bool))
    text = describe(meso)
    attrs = {"format": database.FORMAT, "format_version": database.FORMAT_VERSION, "seed": 7,
             "generator": {"samples": n}, "mesostructure": text, "mesostructure_sha256": description_sha256(text)}
    return data, attrs, database.dataset_attrs(schema, meso), meso


def test_round_trip_attrs_feature_names_and_units(tmp_path):
    data, attrs, attrs_of, meso = fake_database()
    database.write_database(tmp_path / "a.h5", data, attrs, attrs_of)
    read, read_attrs = database.read_database(tmp_path / "a.h5")
    assert set(read) == set(data)
    for name, value in data.items():
        np.testing.assert_array_equal(read[name], value)
    assert read_attrs["seed"] == 7 and json.loads(read_attrs["generator"]) == {"samples": 5}
    assert describe(from_description(read_attrs["mesostructure"])) == describe(meso)
    with h5py.File(tmp_path / "a.h5") as f:
        assert list(f["before/free_position"].attrs["feature_names"]) == ["x_n2", "x_n3", "x_n5", "x_n6"]
        assert f["after/shear_force"].attrs["units"] == "N" and f["after/shear_force"].attrs["role"] == "history"
        assert f["before/free_position"].attrs["role"] == "learned"
        assert list(f["d_eps"].attrs["feature_names"]) == ["d_eps_n", "d_eps_t"]
        features = json.loads(f["schema"].attrs["features"])
        assert features["normal_force"]["role"] == "derived" and features["cell_size"]["names"] == ["l1", "l2"]
        assert "units" in f["schema"].attrs and f["valid"].attrs["description"]
    # no timestamps: the same content gives the same bytes
    database.write_database(tmp_path / "b.h5", data, attrs, attrs_of)
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()


def test_read_rejects_other_versions_and_files(tmp_path):
    data, attrs, attrs_of, _ = fake_database()
    database.write_database(tmp_path / "old.h5", data, {**attrs, "format_version": 1}, attrs_of)
    with pytest.raises(ValueError, match="is not a meso-hmodel-database file of format_version 2"):
        database.read_database(tmp_path / "old.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(ValueError, match="not a readable HDF5 file"):
        database.read_database(tmp_path / "text.h5")


def test_write_is_atomic(tmp_path, monkeypatch):
    data, attrs, attrs_of, _ = fake_database()
    target = tmp_path / "db.h5"
    target.write_bytes(b"precious")
    data["bad"] = np.array([object()], dtype=object)  # h5py cannot store it: the write fails midway
    with pytest.raises(TypeError):
        database.write_database(target, data, attrs, attrs_of)
    assert target.read_bytes() == b"precious" and [p.name for p in tmp_path.iterdir()] == ["db.h5"]
