"""Run files: run.h5 round trip with units and provenance, curve.csv, one-line errors, atomicity."""

from __future__ import annotations

import csv
import json

import h5py
import numpy as np
import pytest

from homogenization.element_test import driver, programme as programmes
from homogenization.output import io
from homogenization.backends import make_cell_model
from warp_hcell.core.cli import UserError
from warp_hcell.mesostructures.hcell import h_cell


@pytest.fixture(scope="module")
def record() -> driver.Record:
    return driver.run(make_cell_model("analytical"), programmes.biaxial(2e5, 0.01, 1e-3), mesostructure=h_cell(55.0),
                      n_orientations=12, snapshot_interval=5, progress=False)


def test_round_trip(tmp_path, record):
    run_path, curve_path = io.write_run(tmp_path, record, parameters={"p0": 2e5, "kn": 2e8}, seed=7)
    assert run_path == tmp_path / "run.h5" and curve_path == tmp_path / "curve.csv"
    stored = io.read_run(run_path)
    back = stored.record
    for name in ("eps11", "eps22", "sigma11", "sigma22", "sigma12", "p", "q", "J", "volume", "newton_iterations",
                 "snapshot_increment", "theta_deg", "weights"):
        assert np.array_equal(getattr(back, name), getattr(record, name)), name
    assert back.stage.tolist() == record.stage.tolist() and back.snapshot_stage.tolist() == record.snapshot_stage.tolist()
    assert back.programme == record.programme and back.backend == "analytical" and back.V0 == record.V0
    assert set(back.snapshots) == set(record.snapshots)
    assert np.array_equal(back.snapshots["closed1"], record.snapshots["closed1"])
    assert np.array_equal(back.final_state["y2"], record.final_state["y2"])
    assert np.array_equal(back.diagnostics["n_unconverged"], record.diagnostics["n_unconverged"])
    assert stored.attrs["seed"] == 7 and stored.attrs["parameters"] == {"kn": 2e8, "p0": 2e5}
    assert stored.attrs["volume_rule"].startswith("V = V0*J") and "hexagon" in stored.attrs["volume_rule"]
    for key in ("code_version", "git_revision", "numpy_version", "warp_version", "torch_version", "cpu"):
        assert stored.attrs[key]


def test_datasets_carry_units_and_sign(tmp_path, record):
    path = io.write_run_h5(tmp_path / "run.h5", record, parameters={}, seed=0)
    assert np.array_equal(io.read_run(tmp_path).record.q, record.q)  # a run's folder reads as its run.h5
    with h5py.File(path, "r") as f:
        assert f["history/sigma11"].attrs["units"] == "N/m"
        assert f["history/eps22"].attrs["units"] == "1"
        assert f["history/q"].attrs["sign_convention"] == "compression and contraction positive"
        assert f["history/volume"].attrs["units"] == "m^2"
        assert json.loads(f.attrs["programme"])["steps"][0]["label"] == "iso"


def test_curve_csv(tmp_path, record):
    path = io.write_curve_csv(tmp_path / "curve.csv", record)
    with open(path) as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["stage", "eps11", "eps22", "sigma11", "sigma22", "sigma12", "p", "q", "e"]
    assert len(rows) == record.n_increments + 1
    assert {r[0] for r in rows[1:]} == {"iso", "shear"}
    values = np.array([[float(v) for v in r[1:]] for r in rows[1:]])
    assert np.array_equal(values[:, 6], record.q) and np.array_equal(values[:, 0], record.eps11)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(UserError, match=f"^{tmp_path / 'nope.h5'}: no such run file$"):
        io.read_run(tmp_path / "nope.h5")
    (tmp_path / "runs" / "dem").mkdir(parents=True)
    (tmp_path / "runs" / "dem" / io.RUN_FILE).write_bytes(b"")
    with pytest.raises(UserError, match=f"^{tmp_path / 'runs'}: a folder without run.h5; the runs in it: "
                                        f"{tmp_path / 'runs' / 'dem' / 'run.h5'}$"):
        io.read_run(tmp_path / "runs")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5 at all")
    with pytest.raises(UserError, match=f"^{bad}: unreadable or corrupt run file"):
        io.read_run(bad)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(UserError, match=r"not a run file \(format attribute is not 'hmodel-run/1'\)$"):
        io.read_run(other)
    with h5py.File(other, "a") as f:
        f.attrs["format"] = io.FORMAT
    with pytest.raises(UserError) as info:
        io.read_run(other)
    assert "\n" not in str(info.value) and "corrupt run file" in str(info.value)


def test_failed_write_keeps_old_output(tmp_path, record):
    path = io.write_run_h5(tmp_path / "run.h5", record, parameters={"a": 1}, seed=0)
    before = path.read_bytes()
    with pytest.raises(TypeError):
        io.write_run_h5(path, record, parameters={"a": object()}, seed=0)  # not JSON-serialisable
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]  # no temporary left behind
