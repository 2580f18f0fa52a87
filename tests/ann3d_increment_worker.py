"""``python tests/ann3d_increment_worker.py IN.npz OUT.npz``: the shipped 3D meso-ANN's compiled increment.

Reads a batch of spatial cell states and probes (``cell_size``, ``free_position``, ``shear_force``,
``d_eps``, and ``index``, a sub-batch to evaluate on its own) and writes every field of
``FastIncrement`` for the whole batch (``whole_*``) and for the sub-batch (``part_*``). The
invariance tests run it in a subprocess compiled for another CPU (``NUMBA_CPU_NAME``).
"""

import sys

import numpy as np

from homogenization.backends.ann import AnnCell3D
from warp_hcell.core.parameters import ContactLaw


def main(source: str, target: str) -> None:
    data = np.load(source)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    index = data["index"]
    fast = AnnCell3D(ContactLaw(), 0.5).fast
    whole = fast(*state, data["d_eps"])._asdict()
    part = fast(*(a[index] for a in state), data["d_eps"][index])._asdict()
    np.savez(target, **{f"whole_{k}": np.asarray(v) for k, v in whole.items()},
             **{f"part_{k}": np.asarray(v) for k, v in part.items()})


if __name__ == "__main__":
    main(*sys.argv[1:3])
