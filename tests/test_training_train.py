"""Training on a small DEM database made in the test: learned rates, determinism, CLI outputs and errors."""

import json

import pytest
import torch

from dem_database import build
from training.checkpoint import load_checkpoint
from training.dataset import Tensors, load_database
from training.network import PAIR_FEATURES, n_features
from training.train import TrainConfig, evaluate, fit, main, run, sliding_light

CONFIG = TrainConfig(hidden=(32, 32), epochs=150, batch_size=64, lr=3e-3, patience=150, threads=1, rollout=False)


@pytest.fixture(scope="module")
def db_path(tmp_path_factory):
    return build(tmp_path_factory.mktemp("db") / "small.h5", precompression=(0.0, 2e-3, 1e-2), n_directions=8,
                 spacing=1e-2, leg_length=0.1, probes_per_state=3, threads=1)


@pytest.fixture(scope="module")
def fitted(db_path):
    db = load_database(db_path)
    return db, fit(db, CONFIG)


def test_the_network_learns_the_free_dof_rates(fitted):
    """A predictor that ignores the state (the mean rate) has R^2 = 0; the trained one does far better."""
    db, result = fitted
    r2 = evaluate(result.net, db, result.split.val)
    assert min(r2["rate"].values()) > 0.8
    assert min(r2["moment_increment"].values()) > 0.8


def test_the_same_seed_gives_a_bit_identical_network(fitted):
    db, result = fitted
    again = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2}))
    twice = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2}))
    for a, b in zip(again.net.state_dict().values(), twice.net.state_dict().values()):
        assert torch.equal(a, b)


def test_cli_writes_model_metadata_with_r2_and_rollout(db_path, tmp_path, capsys):
    out = tmp_path / "m.pt"
    assert main(["--data", str(db_path), "--out", str(out), "--epochs", "3", "--hidden", "8,8", "--threads", "1"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert set(meta["metrics_r2"]["test"]) == {"rate", "relaxation", "moment_increment"}
    assert set(meta["metrics_r2"]["test"]["rate"]) == {"x_n2", "x_n3", "x_n5", "x_n6"}
    roll = meta["rollout"]["increment_0.0001"]
    assert len(roll["per_path"]) == 12 and roll["max"] >= roll["median"] > 0
    assert meta["mesostructure_sha256"] and meta["schema"]["pairs"]
    net, _ = load_checkpoint(out)
    assert net.hidden == (8, 8)
    assert (tmp_path / "m_learning_curve.png").is_file()
    assert "rollout error" in capsys.readouterr().out



def test_cli_load_features_option_reaches_the_saved_network(db_path, tmp_path):
    out = tmp_path / "m.pt"
    assert main(["--data", str(db_path), "--out", str(out), "--epochs", "2", "--hidden", "8", "--threads", "1",
                 "--no-rollout", "--load-features"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["architecture"]["load_features"] is True and meta["config"]["load_features"] is True
    net, _ = load_checkpoint(out)
    n_active = int(net.active.sum())
    assert net.load_features and net.mlp[0].in_features == n_features(net.n_free, n_active) + n_active


def test_sliding_light_flags_a_sliding_contact_beside_a_lightly_loaded_one(fitted):
    """Raw pair features (overlap / D, contact, ..., friction ratio) written by hand for four samples."""
    _, result = fitted
    net = result.net
    n_active, base = int(net.active.sum()), 4 + 2 * net.n_free
    feats = torch.zeros(4, base + len(PAIR_FEATURES) * n_active, dtype=torch.float64)
    pair = feats[:, base:].view(4, n_active, len(PAIR_FEATURES))
    col = {name: PAIR_FEATURES.index(name) for name in ("overlap", "contact", "friction_ratio")}
    pair[:, 0, col["overlap"]], pair[:, 1, col["overlap"]] = 1e-3, 1e-5  # 1 % of the largest normal force
    pair[:, :2, col["contact"]] = 1.0
    pair[0, 0, col["friction_ratio"]] = -1.0  # sliding beside the light contact: flagged
    pair[1, 0, col["friction_ratio"]] = -0.99  # sticking: not flagged
    pair[2, 0, col["friction_ratio"]], pair[2, 1, col["overlap"]] = 1.0, 5e-4  # the second one carries 50 %
    pair[3, 1, col["friction_ratio"]] = 1.0  # the light contact itself slides: flagged
    data = Tensors(feats, torch.ones(4, 1), torch.zeros(4, net.n_free), torch.zeros(4, net.n_free), torch.ones(4, 1))
    assert sliding_light(net, data).tolist() == [True, False, False, True]


def test_a_sliding_weight_of_one_changes_no_bit(fitted):
    db, _ = fitted
    config = TrainConfig(**{**CONFIG.__dict__, "epochs": 2})
    plain = fit(db, config)
    heavy = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2, "sliding_weight": 10.0}))
    one = fit(db, TrainConfig(**{**CONFIG.__dict__, "epochs": 2, "sliding_weight": 1.0}))
    assert all(torch.equal(a, b) for a, b in zip(plain.net.state_dict().values(), one.net.state_dict().values()))
    assert not all(torch.equal(a, b) for a, b in zip(plain.net.state_dict().values(), heavy.net.state_dict().values()))

def test_cli_refuses_to_overwrite_and_reports_bad_data_in_one_line(db_path, tmp_path, capsys):
    out = tmp_path / "m.pt"
    out.write_text("keep me")
    assert run(["--data", str(db_path), "--out", str(out)]) == 2
    assert out.read_text() == "keep me"
    assert run(["--data", str(tmp_path / "none.h5"), "--out", str(tmp_path / "n.pt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "exists" in err[0] and "no such database" in err[1]
