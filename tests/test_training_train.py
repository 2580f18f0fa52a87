"""Training on a real (tiny) generated database: stated loss, determinism, CLI outputs and errors.

The database is made inside the test by the project's generator with the analytical
backend (the DEM reproduces it to 3-4 digits, spec section 10):
``python -m warp_hcell.generate --backend analytical --samples 6000 --n-alpha0 4
--n-directions 8 --seed 0 --clean``.
"""

import json

import numpy as np
import pytest
import torch

from training.checkpoint import load_checkpoint
from training.dataset import load_database
from training.train import TrainConfig, evaluate, fit, main, run
from warp_hcell import generate

CONFIG = TrainConfig(epochs=25, batch_size=256, lr=1e-2, patience=25, threads=2)
STATED_VAL_LOSS = 0.08
"""MSE of z-scored rates reached on the tiny database after 25 epochs (measured 0.067)."""


@pytest.fixture(scope="module")
def db_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("db") / "tiny.h5"
    argv = ["--backend", "analytical", "--samples", "6000", "--n-alpha0", "4", "--n-directions", "8",
            "--seed", "0", "--clean", "--out", str(path)]
    assert generate.main(argv) == 0
    return path


@pytest.fixture(scope="module")
def fitted(db_path):
    db = load_database(db_path)
    return db, fit(db, CONFIG)


def test_training_on_a_small_generated_database_reaches_the_stated_loss(fitted):
    db, result = fitted
    history = result.history
    assert min(history["val_loss"]) < STATED_VAL_LOSS
    assert history["val_loss"][history["best_epoch"] - 1] == min(history["val_loss"])
    assert history["train_loss"][-1] < 0.5 * history["train_loss"][0]
    metrics = evaluate(result.net, db, result.split.val)
    assert set(metrics["increment"]) == {"d_alpha", "dN1", "dN2", "dT1"}
    assert min(metrics["increment"].values()) > 0.7  # measured 0.81 (dT1) to 0.99 (dN1)
    assert min(metrics["value"].values()) > 0.9999


def test_the_same_seed_gives_a_bit_identical_network(fitted):
    db, result = fitted
    again = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2}))
    twice = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2}))
    for key, value in again.net.state_dict().items():
        assert torch.equal(value, twice.net.state_dict()[key]), key
    assert again.history["train_loss"] == twice.history["train_loss"]


def test_cli_writes_model_metadata_and_curve_and_reports_r2(db_path, tmp_path, capsys):
    out = tmp_path / "model.pt"
    argv = ["--data", str(db_path), "--out", str(out), "--epochs", "3", "--hidden", "8,8", "--threads", "1"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "R^2  val: d_alpha=" in printed and "R^2 test:" in printed and "T1=" in printed
    net, meta = load_checkpoint(out)
    assert net.hidden == (8, 8)
    assert meta["training_data"]["sha256"] == load_database(db_path).sha256
    assert meta["contact_law"] == {"kn": 2e8, "kt_over_kn": 0.5, "phi_g_deg": 30.0} and meta["radius"] == 0.5
    assert set(meta["metrics_r2"]) == {"train", "val", "test"}
    assert (tmp_path / "model_learning_curve.png").stat().st_size > 1000
    assert json.loads(out.with_suffix(".json").read_text())["config"]["hidden"] == [8, 8]


def test_cli_refuses_to_overwrite_and_reports_bad_data_in_one_line(db_path, tmp_path, capsys):
    out = tmp_path / "model.pt"
    out.write_bytes(b"keep me")
    assert run(["--data", str(db_path), "--out", str(out), "--epochs", "1"]) == 2
    assert out.read_bytes() == b"keep me"
    err = capsys.readouterr().err.strip()
    assert err.endswith("exists; pass --overwrite to replace it") and "\n" not in err
    assert run(["--data", str(tmp_path / "missing.h5"), "--out", str(tmp_path / "m2.pt")]) == 2
    assert "missing.h5: no such database file" in capsys.readouterr().err
    assert not (tmp_path / "m2.pt").exists()


def test_bad_cli_values_exit_with_code_2(db_path, tmp_path):
    for bad in (["--epochs", "0"], ["--hidden", "8,x"], ["--lr", "-1"]):
        with pytest.raises(SystemExit) as info:
            main(["--data", str(db_path), "--out", str(tmp_path / "m.pt"), *bad])
        assert info.value.code == 2


def test_split_of_the_fit_is_by_path(fitted):
    db, result = fitted
    split = result.split
    assert not set(db.path_id[split.train]) & set(db.path_id[split.val])
    assert not set(db.path_id[split.train]) & set(db.path_id[split.test])
    assert np.isclose(result.normalisation.feature_mean[2], np.radians(db.inputs[split.train, 2]).mean())
