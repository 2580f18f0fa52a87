"""``python tests/ann3d_increment_worker.py IN.npz OUT.npz [K]``: the shipped 3D meso-ANN's compiled increment.

Reads a batch of spatial cell states and probes (``cell_size``, ``free_position``, ``shear_force``,
``d_eps``, and ``index``, a sub-batch to evaluate on its own) and writes every field of
``FastIncrement`` for the whole batch (``whole_*``) and for the sub-batch (``part_*``). The
invariance tests run it in a subprocess compiled for another CPU (``NUMBA_CPU_NAME``). With K > 0,
the increment with up to K equilibrium corrections (``FastAdvance(corrections=K)``), and also the
corrections' counts (``FastAdvance.last_corrections``). With ``large_axial`` after K, the network is
``relaxing_network`` of ``benchmarks/cells/large_axial.toml`` instead of the shipped model.
"""

import sys
from pathlib import Path

import numpy as np
import torch

from homogenization.ann.cell import AnnCell3D
from training.cell_physics import CellSchema
from training.inference import FastAdvance
from training.network import MesoNet
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.builders import mesostructure_arg

LARGE_AXIAL = Path(__file__).resolve().parents[1] / "benchmarks" / "cells" / "large_axial.toml"


def relaxing_network(spec: str = str(LARGE_AXIAL)) -> MesoNet:
    """A network of the cell ``spec`` whose output layer is zero: its first guess is the relaxation along
    the unbalanced force alone, the same in torch and compiled (no weight enters it)."""
    meso, law = mesostructure_arg(spec).build(None), ContactLaw()
    schema = CellSchema.from_arrays(radius=meso.radius, reference_position=meso.position,
                                    reference_cell_size=meso.cell_size, driven=meso.driven, pairs=meso.pairs,
                                    outer=meso.outer, kn=law.kn, kt=law.kt, mu=law.mu,
                                    contact_tolerance=meso.contact_tolerance)
    net = MesoNet(schema, torch.ones(schema.n_pairs, dtype=torch.bool), hidden=(16,))
    with torch.no_grad():
        net.mlp[-1].weight.zero_()
        net.mlp[-1].bias.zero_()
    return net


def fields(fast: FastAdvance, state, d_eps) -> dict:
    """Every field of the increment, and of its corrections where there are any."""
    out = fast(*state, d_eps)._asdict()
    corrections = fast.last_corrections()
    return out if corrections is None else {**out, **corrections._asdict()}


def main(source: str, target: str, corrections: str = "0", network: str = "shipped") -> None:
    data = np.load(source)
    state = tuple(data[name] for name in ("cell_size", "free_position", "shear_force"))
    index = data["index"]
    net = relaxing_network() if network == "large_axial" else AnnCell3D(ContactLaw(), 0.5).net
    fast = FastAdvance(net, int(corrections))
    whole = fields(fast, state, data["d_eps"])
    part = fields(fast, tuple(a[index] for a in state), data["d_eps"][index])
    np.savez(target, **{f"whole_{k}": np.asarray(v) for k, v in whole.items()},
             **{f"part_{k}": np.asarray(v) for k, v in part.items()})


if __name__ == "__main__":
    main(*sys.argv[1:5])
