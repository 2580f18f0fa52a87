"""Checkpoints: state_dict + JSON round trip, and one-line errors for bad or mismatched files."""

import json

import numpy as np
import pytest
import torch

from training.checkpoint import CheckpointError, check_compatible, load_checkpoint, metadata_path, save_checkpoint
from training.network import CellNet

LAW = {"kn": 2e8, "kt_over_kn": 0.5, "phi_g_deg": 30.0}


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(0)
    net = CellNet((8, 6), kn=2e8, diameter=1.0, mu=0.5)
    net.set_normalisation(np.arange(12.0), np.full(12, 2.0), np.ones(4), np.full(4, 3.0))
    path = tmp_path / "model.pt"
    save_checkpoint(path, net, {"contact_law": LAW, "radius": 0.5, "metrics_r2": {"val": {"x": 0.5}}})
    return path, net


def test_round_trip_restores_the_same_network_and_metadata(saved):
    path, net = saved
    loaded, meta = load_checkpoint(path)
    x = torch.from_numpy(np.random.default_rng(0).normal(size=(5, 8)))
    assert torch.equal(loaded.predict(x), net.predict(x))
    assert meta["architecture"]["hidden"] == [8, 6] and meta["metrics_r2"] == {"val": {"x": 0.5}}
    assert meta["normalisation"]["feature_mean"] == list(np.arange(12.0))
    assert meta["scales"] == {"kn": 2e8, "diameter": 1.0, "mu": 0.5}
    assert sorted(p.name for p in path.parent.iterdir()) == ["model.json", "model.pt"]  # no temporary left
    assert all(p.stat().st_mode & 0o777 == 0o644 for p in path.parent.iterdir())


def test_the_state_dict_file_holds_tensors_only(saved):
    state = torch.load(saved[0], weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in state.values())


def _corrupt(path, case):
    json_path = metadata_path(path)
    if case == "pt_missing":
        path.unlink()
    elif case == "json_missing":
        json_path.unlink()
    elif case == "pt_garbage":
        path.write_bytes(b"\x00garbage" * 20)
    elif case == "json_garbage":
        json_path.write_text("{not json")
    elif case == "json_format":
        json_path.write_text(json.dumps({"format": "other"}))
    else:
        meta = json.loads(json_path.read_text())
        if case == "hidden_mismatch":
            meta["architecture"]["hidden"] = [8, 8, 8]
        elif case == "activation":
            meta["architecture"]["activation"] = "relu"
        elif case == "scales":
            meta["scales"]["kn"] = 1e7
        json_path.write_text(json.dumps(meta))


@pytest.mark.parametrize("case, message", [
    ("pt_missing", "no such model file"),
    ("json_missing", "no such model metadata file"),
    ("pt_garbage", "not a readable torch state_dict"),
    ("json_garbage", "not a valid JSON model metadata file"),
    ("json_format", "not a meso-hmodel-ann metadata file"),
    ("hidden_mismatch", "state_dict does not match the architecture in model.json (hidden = [8, 8, 8])"),
    ("activation", "is not a 8-input tanh CellNet"),
    ("scales", "scales in the state_dict differ from model.json"),
])
def test_bad_model_files_give_one_line_errors(saved, case, message):
    path, _ = saved
    _corrupt(path, case)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_model_for_another_contact_law_or_radius_is_refused(saved):
    _, meta = load_checkpoint(saved[0])
    check_compatible(meta, radius=0.5, source="m.pt", **LAW)
    with pytest.raises(CheckpointError, match=r"m.pt: model trained with kn = 200000000.0, this run uses kn = 1e\+07"):
        check_compatible(meta, radius=0.5, source="m.pt", **{**LAW, "kn": 1e7})
    with pytest.raises(CheckpointError, match="radius = 0.5, this run uses radius = 1"):
        check_compatible(meta, radius=1.0, source="m.pt", **LAW)
