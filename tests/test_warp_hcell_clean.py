"""Tests of warp_hcell.clean: each rule, the recorded counts, the in-place atomic rewrite, the CLI."""

import json

import numpy as np
import pytest

from warp_hcell import clean, database

COL = {name: i for i, name in enumerate(database.STATE_FEATURES)}


def fake_samples(n):
    rng = np.random.default_rng(1)
    samples = database.sample_arrays(rng.random((n, 2)), rng.random((n, 13)), rng.random((n, 13)))
    samples.update(path_id=np.arange(n), probe_id=np.zeros(n, np.int64), alpha0_deg=np.full(n, 55.0),
                   state_index=np.arange(n), converged=np.ones(n, bool), valid=np.ones(n, bool))
    return samples, {"observables": samples["pre_state"], "backend/position": rng.random((n, 6, 2))}


def pathological_samples():
    """Six samples: healthy, alpha out of range (pre), mechanism (post), unconverged, NaN, two reasons."""
    samples, states = fake_samples(6)
    for table in (samples["pre_state"], samples["post_state"]):
        table[:, COL["alpha_deg"]] = 55.0
        table[:, [COL["closed1"], COL["closed2"]]] = 1.0
    samples["pre_state"][1, COL["alpha_deg"]] = 29.0
    samples["post_state"][2, [COL["closed1"], COL["closed2"]]] = 0.0
    samples["converged"][3] = False
    samples["outputs"][4, 1] = np.nan
    samples["post_state"][5, COL["alpha_deg"]] = 90.5
    samples["converged"][5] = False
    samples["pre_state"][0, COL["alpha_deg"]] = 30.0 - 4e-15  # rounding at alpha0 = 30 is admissible
    return samples, states


def test_each_rule_and_counts():
    samples, _ = pathological_samples()
    valid, attrs = clean.clean_samples(samples)
    np.testing.assert_array_equal(valid, [True, False, False, False, False, False])
    assert attrs["removed_alpha_range"] == 2 and attrs["removed_mechanism"] == 1
    assert attrs["removed_unconverged"] == 2 and attrs["removed_non_finite"] == 1
    assert attrs["n_removed"] == 5 and attrs["n_valid"] == 1 and attrs["cleaned"]
    assert json.loads(attrs["cleaning"])["removed"]["unconverged"] == 2
    valid, attrs = clean.not_cleaned(samples)
    assert valid.all() and not attrs["cleaned"] and attrs["n_removed"] == 0


def test_cli_cleans_in_place(tmp_path, capsys):
    samples, states = pathological_samples()
    path = tmp_path / "db.h5"
    database.write_database(path, samples, states, {"format": database.FORMAT, "format_version": 1, "seed": 2})
    assert clean.main([str(path)]) == 0
    assert "1 valid, 5 removed" in capsys.readouterr().out
    read, read_states, attrs = database.read_database(path)
    np.testing.assert_array_equal(read["valid"], [True, False, False, False, False, False])
    np.testing.assert_array_equal(read["inputs"], samples["inputs"])
    assert attrs["seed"] == 2 and attrs["removed_mechanism"] == 1 and "backend/position" in read_states
    assert not list(tmp_path.glob(".*tmp"))


@pytest.mark.parametrize("make, message", [
    (lambda p: None, "no such database file"),
    (lambda p: p.write_text("not hdf5"), "db.h5"),
])
def test_cli_errors_exit_2(tmp_path, capsys, make, message):
    path = tmp_path / "db.h5"
    make(path)
    with pytest.raises(SystemExit) as exc:
        clean.main([str(path)])
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error:" in last and message in last
    if path.exists():
        assert path.read_text() == "not hdf5"
