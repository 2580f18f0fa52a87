"""Tests of warp_hcell.clean: each rule, what is kept (mechanism, perturbed), the recorded counts,
the in-place atomic rewrite, the CLI."""

import json

import numpy as np

from test_warp_hcell_database import fake_database
from warp_hcell.database import clean, format as database
from warp_hcell import clean as clean_command


def pathological():
    """Six samples: healthy, unconverged, NaN after, inf in d_eps, two reasons, mechanism + perturbed."""
    data, attrs, attrs_of, _ = fake_database(6)
    data["converged"][[1, 4]] = False
    data["after/normal_force"][2, 3] = np.nan
    data["d_eps"][3, 0] = np.inf
    data["before/unbalanced"][4, 0] = np.nan
    data["mechanism"][5] = True
    return data, attrs, attrs_of


def test_each_rule_and_counts_mechanisms_kept():
    data, _, _ = pathological()
    valid, attrs = clean.clean_samples(data)
    np.testing.assert_array_equal(valid, [True, False, False, False, False, True])
    assert attrs["removed_unconverged"] == 2 and attrs["removed_non_finite"] == 3
    assert attrs["n_removed"] == 4 and attrs["n_valid"] == 2 and attrs["cleaned"]
    assert json.loads(attrs["cleaning"])["removed"] == {"unconverged": 2, "non_finite": 3}


def test_not_cleaned_keeps_everything():
    data, _, _ = pathological()
    valid, attrs = clean.not_cleaned(data)
    assert valid.all() and not attrs["cleaned"] and attrs["n_removed"] == 0


def test_cli_cleans_in_place_and_keeps_attrs(tmp_path, capsys):
    data, attrs, attrs_of = pathological()
    path = tmp_path / "db.h5"
    database.write_database(path, data, attrs, attrs_of)
    assert clean_command.main([str(path)]) == 0
    assert "2 valid, 4 removed" in capsys.readouterr().out
    read, read_attrs = database.read_database(path)
    np.testing.assert_array_equal(read["valid"], [True, False, False, False, False, True])
    assert read_attrs["cleaned"] and read_attrs["seed"] == 7
    assert database.read_attrs_of(path)["before/free_position"]["role"] == "learned"


def test_cli_errors_exit_2(tmp_path, capsys):
    assert clean_command.main([str(tmp_path / "missing.h5")]) == 2
    assert "no such database file" in capsys.readouterr().err
    (tmp_path / "text.h5").write_text("not hdf5")
    assert clean_command.main([str(tmp_path / "text.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a readable HDF5 file" in err[0]
