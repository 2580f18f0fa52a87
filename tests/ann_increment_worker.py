"""``python tests/ann_increment_worker.py IN.npz OUT.npz``: the shipped meso-ANN's compiled increment and tangent.

Reads a batch of cell states and probes (``cell_size``, ``free_position``, ``shear_force``,
``d_eps``, and ``index``, a sub-batch to evaluate on its own) and writes every field of
``FastIncrement`` and the tangent for the whole batch (``whole_*``) and for the sub-batch
(``part_*``). The invariance tests run it in a subprocess whose compiler settings differ from
the test process (``NUMBA_CPU_NAME``: narrower vectors; ``OPENBLAS_CORETYPE``: other BLAS kernels).
"""

import sys

import numpy as np

from homogenization.ann.cell import AnnCell
from training.inference import FastAdvance
from warp_hcell.core.parameters import ContactLaw


def evaluate(fast: FastAdvance, state: tuple[np.ndarray, ...], d_eps: np.ndarray) -> dict[str, np.ndarray]:
    """Every field of the increment and the tangent, keyed by name."""
    increment, tangent = fast.increment(*state, d_eps, with_tangent=True)
    return {**{name: np.asarray(value) for name, value in increment._asdict().items()}, "tangent": tangent}


def main(source: str, target: str) -> None:
    data = np.load(source)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    index = data["index"]
    fast = FastAdvance(AnnCell(ContactLaw(), 0.5).net)
    whole = evaluate(fast, state, data["d_eps"])
    part = evaluate(fast, tuple(a[index] for a in state), data["d_eps"][index])
    np.savez(target, **{f"whole_{k}": v for k, v in whole.items()}, **{f"part_{k}": v for k, v in part.items()})


if __name__ == "__main__":
    main(*sys.argv[1:3])
