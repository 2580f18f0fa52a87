"""``python tests/ann3d_increment_worker.py IN.npz OUT.npz [K]``: the shipped 3D meso-ANN's compiled increment.

Reads a batch of spatial cell states and probes (``cell_size``, ``free_position``, ``shear_force``,
``d_eps``, and ``index``, a sub-batch to evaluate on its own) and writes every field of
``FastIncrement`` for the whole batch (``whole_*``) and for the sub-batch (``part_*``). The
invariance tests run it in a subprocess compiled for another CPU (``NUMBA_CPU_NAME``). With K > 0,
the increment with up to K equilibrium corrections (``FastAdvance(corrections=K)``), and also the
corrections' ``force_ratio`` and ``steps`` (``FastAdvance.last_corrections``).
"""

import sys

import numpy as np

from homogenization.backends.ann import AnnCell3D
from training.inference import FastAdvance
from warp_hcell.core.parameters import ContactLaw


def fields(fast: FastAdvance, state, d_eps) -> dict:
    """Every field of the increment, and of its corrections where there are any."""
    out = fast(*state, d_eps)._asdict()
    corrections = fast.last_corrections()
    return out if corrections is None else {**out, **corrections._asdict()}


def main(source: str, target: str, corrections: str = "0") -> None:
    data = np.load(source)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    index = data["index"]
    fast = FastAdvance(AnnCell3D(ContactLaw(), 0.5).net, int(corrections))
    whole = fields(fast, state, data["d_eps"])
    part = fields(fast, tuple(a[index] for a in state), data["d_eps"][index])
    np.savez(target, **{f"whole_{k}": np.asarray(v) for k, v in whole.items()},
             **{f"part_{k}": np.asarray(v) for k, v in part.items()})


if __name__ == "__main__":
    main(*sys.argv[1:4])
