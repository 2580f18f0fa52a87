"""The learning database and the meso-ANN take the dimension of the cell from the cell.

The 2D digests below were computed with the code at main before the database, the training
and the ANN backend learnt the spatial cell (commit e8c08f1): a tiny 2D database of a fixed
seed and a few epochs of training on it must stay bit for bit what they were.
"""

import hashlib
from pathlib import Path

import numpy as np
import pytest

from warp_hcell.database import format as database, generate
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.hcell import StartCells, h_cell
from warp_hcell.core.parameters import DatabaseSettings

DATA = Path(__file__).resolve().parents[1] / "warp_hcell" / "data"
TINY = DatabaseSettings(samples=300, chunk_size=150, precompression=(0.0, 1e-3), n_directions=6,
                        sample_spacing=1e-2, leg_length=0.03, leg_volumetric=0.05, leg_refinement=1)
H_CELL_DIGEST = "6533de518fdcfa63e117be74a336fb40b4304fda64d0badbfdad65e534ef2c28"
"""sha256 of the arrays of the H-cell database of ``_h_cell_database`` at main (54 datasets)."""
FINE_DIGEST = "efd43f5feb2fee41fcb9e5f7644683f431bb441e786c5db5bdadcbdba247786d"
"""The same for the cell with a fine grain (``h_cell_fine_grain.toml``)."""
WEIGHTS_DIGEST = "bdf459aa0295c7df733fa81911f4a79ac2046ed4782987a9a554476b7c0f9344"
"""sha256 of the state_dict after ``_tiny_fit`` on the H-cell database at main."""


@pytest.fixture(autouse=True)
def fixed_revision(monkeypatch):
    monkeypatch.setattr(generate, "provenance", lambda: {"git_revision": "pinned"})


def array_digest(data: dict) -> str:
    """sha256 over the names, dtypes, shapes and bytes of ``data``'s arrays, in name order."""
    h = hashlib.sha256()
    for name in sorted(data):
        a = np.ascontiguousarray(data[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _h_cell_database(out: Path) -> Path:
    starts = StartCells(n_alpha0=1, alpha0_focus_deg=(55.0,)).build()
    generate.generate(h_cell(), TINY, out, seed=5, starts=starts, threads=1)
    return out


def test_2d_databases_unchanged(tmp_path):
    data, _ = database.read_database(_h_cell_database(tmp_path / "h.h5"))
    assert len(data) == 54
    assert array_digest(data) == H_CELL_DIGEST
    fine = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    generate.generate(fine, TINY, tmp_path / "fine.h5", seed=5, threads=1)
    assert array_digest(database.read_database(tmp_path / "fine.h5")[0]) == FINE_DIGEST


def test_2d_training_unchanged(tmp_path):
    from training.dataset import load_database
    from training.train import TrainConfig, fit

    db = load_database(_h_cell_database(tmp_path / "h.h5"))
    net = fit(db, TrainConfig(hidden=(6,), epochs=3, batch_size=64, seed=2, rollout=False)).net
    h = hashlib.sha256()
    for name, value in net.state_dict().items():
        h.update(name.encode())
        h.update(value.detach().cpu().numpy().tobytes())
    assert h.hexdigest() == WEIGHTS_DIGEST
