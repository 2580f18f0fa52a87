"""Model files: round trip, tensors only, one-line errors, contact-law and mesostructure checks."""

import json

import pytest
import torch

from dem_database import build
from training.checkpoint import check_compatible, check_start_cell, CheckpointError, load_checkpoint, save_checkpoint
from training.train import main
from warp_hcell.mesostructures.files import describe, from_description, load_mesostructure
from warp_hcell.mesostructures.hcell import h_cell


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ckpt")
    db = build(folder / "db.h5", precompression=(0.0, 2e-3), n_directions=6, spacing=1e-2, leg_length=0.06,
               threads=1)
    assert main(["--data", str(db), "--out", str(folder / "m.pt"), "--epochs", "2", "--hidden", "8",
                 "--threads", "1", "--no-rollout"]) == 0
    return folder / "m.pt"


def test_round_trip_restores_the_same_network(saved):
    net, meta = load_checkpoint(saved)
    again, _ = load_checkpoint(saved)
    f64 = dict(dtype=torch.float64)
    state = (torch.tensor([[2.3, 1.6]], **f64), torch.tensor([[0.5, -0.5, -0.5, 0.5]], **f64), torch.zeros(1, 15, **f64))
    d = torch.tensor([[1e-4, -2e-4]], **f64)
    with torch.no_grad():
        assert torch.equal(net.displacement(*state, d), again.displacement(*state, d))
    assert meta["format_version"] == 2 and len(meta["mesostructure_sha256"]) == 64



def test_saving_the_same_network_twice_gives_the_same_bytes(saved, tmp_path):
    """The model file depends on the network and its metadata only (not on the temporary name
    of the atomic write): a rerun of a reproducible training gives a byte-identical .pt."""
    net, meta = load_checkpoint(saved)
    first, _ = save_checkpoint(tmp_path / "a" / "m.pt", net, meta)
    second, _ = save_checkpoint(tmp_path / "b" / "m.pt", net, meta)
    assert first.read_bytes() == second.read_bytes()

def test_the_state_dict_file_holds_tensors_only(saved):
    state = torch.load(saved, weights_only=True)
    assert all(isinstance(v, torch.Tensor) for v in state.values())


@pytest.mark.parametrize("case, message", [("no_pt", "no such model file"), ("bad_json", "not a valid JSON"),
                                           ("version1", "format_version 1"), ("bad_pt", "not a readable torch")])
def test_bad_model_files_give_one_line_errors(saved, tmp_path, case, message):
    pt, js = tmp_path / "m.pt", tmp_path / "m.json"
    pt.write_bytes(saved.read_bytes())
    meta = json.loads(saved.with_suffix(".json").read_text())
    js.write_text(json.dumps(meta))
    if case == "no_pt":
        pt.unlink()
    elif case == "bad_json":
        js.write_text("{")
    elif case == "version1":
        js.write_text(json.dumps({**meta, "format_version": 1}))
    else:
        pt.write_text("garbage")
    with pytest.raises(CheckpointError, match=message) as info:
        load_checkpoint(pt)
    assert "\n" not in str(info.value)


def test_another_contact_law_or_mesostructure_is_refused(saved):
    _, meta = load_checkpoint(saved)
    check_compatible(meta, kn=2e8, kt_over_kn=0.5, phi_g_deg=30.0, source="m")
    with pytest.raises(CheckpointError, match="kn = 200000000.0, this run uses kn = 1e\\+08"):
        check_compatible(meta, kn=1e8, kt_over_kn=0.5, phi_g_deg=30.0, source="m")
    trained = from_description(meta["mesostructure"])
    check_start_cell(meta, trained, source="m")
    with pytest.raises(CheckpointError, match="another learning state"):
        check_start_cell(meta, load_mesostructure("warp_hcell/data/h_cell_lateral_0.7D.toml"), source="m")


def test_cells_between_the_start_cells_of_the_database_are_accepted(saved):
    """Same learning state: accepted within the range of the recorded start cells, refused outside."""
    _, meta = load_checkpoint(saved)
    assert meta["start_mesostructures"] == [meta["mesostructure"]]  # what the database recorded
    r = float(from_description(meta["mesostructure"]).radius[0])
    with pytest.raises(CheckpointError, match="outside the range"):
        check_start_cell(meta, h_cell(47.0, r), source="m")  # one start cell: only itself
    spanned = dict(meta, start_mesostructures=[describe(h_cell(40.0, r)), describe(h_cell(55.0, r))])
    check_start_cell(spanned, h_cell(47.0, r), source="m")
    for outside in (35.0, 60.0):
        with pytest.raises(CheckpointError, match="outside the range of the cells its database was explored from"):
            check_start_cell(spanned, h_cell(outside, r), source="m")
