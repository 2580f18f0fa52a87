"""The tiny 2D database and training of the determinism tests, and the committed reference weights.

``python tests/determinism_reference.py`` (from the repository root) trains the tiny network
and writes its weights to ``REFERENCE``; run it only when the training's numerics change on
purpose, and say so in the commit. The DEM database is the same bits on any x86-64 CPU under
Linux with glibc, FMA or not (``tests/test_database_dimension.py`` holds its digests); torch's
training is not (MKL, oneDNN and ATen pick kernels by CPU), so the test compares the weights
with ``WEIGHTS_RTOL`` (docs/determinism.md).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from warp_hcell.core.parameters import DatabaseSettings
from warp_hcell.database import generate
from warp_hcell.mesostructures.hcell import StartCells, h_cell

REFERENCE = Path(__file__).resolve().parent / "data" / "determinism" / "tiny_fit_2d.npz"
"""state_dict of ``tiny_fit`` on ``h_cell_database``, one array per entry (float64; ``active`` bool)."""
TINY = DatabaseSettings(samples=300, chunk_size=150, precompression=(0.0, 1e-3), n_directions=6,
                        sample_spacing=1e-2, leg_length=0.03, leg_volumetric=0.05, leg_refinement=1)
WEIGHTS_RTOL = 1e-6
"""Largest difference of a tensor of ``tiny_fit`` from the reference, relative to the tensor's
largest magnitude. Measured on one AVX-512 CPU under every setting of ``make determinism``:
at most 1.2e-9 (ATEN_CPU_CAPABILITY=default: another tanh and other summation orders);
one more epoch of training moves a tensor by 0.33."""


def h_cell_database(out: Path) -> Path:
    """Write the tiny database of the H-cell at alpha0 = 55 deg (seed 5, one thread) to ``out``; the
    caller pins the git revision written in it."""
    starts = StartCells(n_alpha0=1, alpha0_focus_deg=(55.0,)).build()
    generate.generate(h_cell(), TINY, out, seed=5, starts=starts, threads=1)
    return out


def tiny_fit(path: Path, epochs: int = 3) -> dict[str, np.ndarray]:
    """state_dict of a 6-wide network trained ``epochs`` epochs on the database ``path`` (seed 2, no rollout)."""
    from training.dataset import load_database
    from training.fitting import TrainConfig, fit

    net = fit(load_database(path), TrainConfig(hidden=(6,), epochs=epochs, batch_size=64, seed=2, rollout=False)).net
    return {name: value.detach().cpu().numpy().copy() for name, value in net.state_dict().items()}


def weight_differences(weights: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict[str, float]:
    """Per float tensor: max |w - w_ref| / max |w_ref| (0 where the reference is all zeros and so is w)."""
    out = {}
    for name, ref in reference.items():
        if ref.dtype.kind == "f":
            scale = float(np.abs(ref).max()) if ref.size else 0.0
            diff = float(np.abs(weights[name] - ref).max()) if ref.size else 0.0
            out[name] = diff / scale if scale > 0.0 else diff
    return out


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        generate_provenance = generate.provenance
        generate.provenance = lambda: {"git_revision": "pinned"}
        try:
            weights = tiny_fit(h_cell_database(Path(tmp) / "h.h5"))
        finally:
            generate.provenance = generate_provenance
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    np.savez(REFERENCE, **weights)
    print(f"wrote {REFERENCE} ({len(weights)} tensors)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
