"""Training on a small DEM database made in the test: learned rates, determinism, CLI outputs and errors."""

import json

import pytest
import torch

from dem_database import build
from training.checkpoint import load_checkpoint
from training.dataset import Tensors, load_database
from training.network import PAIR_FEATURES, n_features
from training.fitting import TrainConfig, evaluate, fit, sliding_light
from training.train import main, run

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


def test_reexpressed_weights_compute_the_same_function_in_another_normalisation(fitted):
    """Warm start: the start model's layers re-expressed in the new training split's feature scaling
    give the same displacements (to round-off), where copying them unchanged does not."""
    from training.network import MesoNet
    from training.fitting import reexpress

    db, result = fitted
    old = result.net
    new = MesoNet(db.schema, old.active, old.hidden)
    new.set_normalisation(old.feature_mean * 0.7 + 0.3, old.feature_std * 1.9, old.rate_mean - 0.2, old.rate_std * 0.6)
    state = [torch.from_numpy(db.before[k][:500]) for k in ("cell_size", "free_position", "shear_force")]
    d_eps = torch.from_numpy(db.d_eps[:500])
    with torch.no_grad():
        reference = old.displacement(*state, d_eps)
        new.mlp.load_state_dict(old.mlp.state_dict())
        copied = new.displacement(*state, d_eps)
        new.mlp.load_state_dict(reexpress(old, new))
        warm = new.displacement(*state, d_eps)
    scale = reference.abs().max()
    assert (copied - reference).abs().max() > 1e-2 * scale
    assert (warm - reference).abs().max() < 1e-10 * scale


def test_warm_start_begins_at_the_start_model_and_is_declined_for_another_architecture(db_path, tmp_path, capsys):
    start = tmp_path / "start.pt"
    argv = ["--data", str(db_path), "--epochs", "3", "--hidden", "8,8", "--threads", "1", "--no-rollout"]
    assert main([*argv, "--out", str(start)]) == 0
    previous, _ = load_checkpoint(start)
    db = load_database(db_path)
    frozen = fit(db, TrainConfig(hidden=(8, 8), epochs=1, lr=1e-300, threads=1, rollout=False, init_from=str(start)))
    assert frozen.history["warm_start"] == {"from": str(start), "used": True, "reason": None}
    state = [torch.from_numpy(db.before[k]) for k in ("cell_size", "free_position", "shear_force")]
    with torch.no_grad():
        a, b = (net.displacement(*state, torch.from_numpy(db.d_eps)) for net in (previous, frozen.net))
    assert (a - b).abs().max() < 1e-10 * a.abs().max()  # a learning rate of 1e-300 keeps the start model
    capsys.readouterr()
    assert main([*argv, "--hidden", "9,8", "--init-from", str(start), "--out", str(tmp_path / "w.pt")]) == 0
    meta = json.loads((tmp_path / "w.json").read_text())
    assert meta["history"]["warm_start"]["used"] is False and "hidden widths [8, 8]" in meta["history"]["warm_start"]["reason"]
    assert meta["config"]["init_from"] == str(start)
    assert f"warm start from {start} declined: hidden widths [8, 8]" in capsys.readouterr().out
    assert run([*argv, "--init-from", str(tmp_path / "none.pt"), "--out", str(tmp_path / "x.pt")]) == 2
    assert "--init-from" in capsys.readouterr().err and not (tmp_path / "x.pt").exists()


def test_a_split_by_round_keeps_every_earlier_path_in_its_set(db_path):
    """Appending a round's paths moves no earlier path to another set (a warm start never
    validates on its start model's training paths); without rounds it is the usual split."""
    import dataclasses

    import numpy as np

    from training.dataset import split_by_path

    db = load_database(db_path)
    options = {"val_fraction": 0.2, "test_fraction": 0.1, "seed": 3}
    plain, by_round = split_by_path(db, **options), split_by_path(db, **options, by_round=True)
    for name in ("train", "val", "test"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(by_round, name))
    n = db.path_id.size
    grown = dataclasses.replace(db, path_id=np.concatenate([db.path_id, db.path_id.max() + 1 + np.arange(n) // 10]),
                                source_round=np.concatenate([db.source_round, np.ones(n, np.int64)]))
    after = split_by_path(grown, **options, by_round=True)
    for name in ("train", "val", "test"):
        kept = getattr(after, name)
        np.testing.assert_array_equal(kept[kept < n], getattr(plain, name))
        assert np.any(kept >= n)  # the round's paths are split too
    moved = split_by_path(grown, **options)
    assert not np.array_equal(moved.val[moved.val < n], plain.val)  # one permutation of all paths moves them


def test_fit_reports_every_epoch_to_its_progress_callback_and_marks_the_last(db_path):
    seen = []
    config = TrainConfig(hidden=(8,), epochs=6, batch_size=64, threads=1, rollout=False)
    result = fit(load_database(db_path), config, progress=seen.append)
    assert [e.epoch for e in seen] == result.history["epoch"] == [1, 2, 3, 4, 5, 6]
    assert [e.last for e in seen] == [False] * 5 + [True] and all(e.epochs == 6 for e in seen)
    assert [e.val_loss for e in seen] == result.history["val_loss"] and [e.lr for e in seen] == result.history["lr"]


def test_round_share_weights_the_rounds_samples_to_their_share_and_changes_no_bit_without_rounds(fitted):
    """The samples of active-learning rounds carry ``round_share`` of the summed loss weight; a
    database without rounds trains bit-identically whatever the share; with rounds the network changes."""
    import dataclasses

    import numpy as np

    from training.fitting import round_weights

    weight = round_weights(np.array([0, 0, 0, 0, 0, 0, 1, 2]), 0.25).numpy()[:, 0]
    assert weight[:6].tolist() == [1.0] * 6 and weight[6:].sum() / weight.sum() == pytest.approx(0.25, rel=1e-12)
    assert round_weights(np.array([0, 0, 1]), 0.0).numpy().tolist() == [[1.0]] * 3
    assert round_weights(np.array([1, 1]), 0.5).numpy().tolist() == [[1.0]] * 2  # one kind only: no weighting
    db, _ = fitted
    short = {**CONFIG.__dict__, "epochs": 2}
    nets = [fit(d, TrainConfig(**{**short, "round_share": s})).net.state_dict()
            for d, s in ((db, 0.0), (db, 0.5))]
    assert all(torch.equal(a, b) for a, b in zip(*(n.values() for n in nets)))
    grown = dataclasses.replace(db, source_round=(db.path_id % 3 == 0).astype(np.int64))  # a third of the paths a round
    pair = [fit(grown, TrainConfig(**{**short, "round_share": s})) for s in (0.0, 0.5)]
    assert not all(torch.equal(a, b) for a, b in zip(*(p.net.state_dict().values() for p in pair)))
    assert pair[0].history["val_loss"] != pair[1].history["val_loss"]  # the validation loss is weighted too
