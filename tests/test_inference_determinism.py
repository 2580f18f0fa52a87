"""The compiled meso-ANN increment (``training.inference.FastAdvance``, planar and spatial cells) is the same bits on any x86-64 CPU.

Its physics is numba float64 with +, -, *, / and sqrt only (no fastmath, no FMA contraction)
and its perceptron one fixed sequence of float32 fused multiply-adds per cell, whatever the
vector width numba compiles for (``NUMBA_CPU_NAME``). The network here is the H-cell's with
weights drawn by numpy (torch's initialisation is not needed), so the digest does not move when
the shipped model is regenerated. ``make determinism`` runs this under every CPU-feature
setting, ``NUMBA_CPU_NAME`` = generic and haswell among them (docs/determinism.md).
"""

import hashlib

import numpy as np
import pytest
import torch

from training.cell_physics import CellSchema
from training.inference import FastAdvance
from training.network import MesoNet
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.builders import mesostructure_arg
from warp_hcell.mesostructures.hcell import h_cell

INCREMENTS_DIGEST = "b581ffcc9533e44dfff6f62f011dccd34428f227b6ed4ff0d8a331118218d9bf"
"""sha256 of every output and tangent of ``_increments`` (``_digest``)."""
INCREMENTS_3D_DIGEST = "62bb01a6f1a196068a5fe6531e0cdd52541869e2b6ad915e511b0e407faf7b4c"
"""sha256 of every output of ``_increments_3d`` (``_digest``)."""


def _network(meso=None, load_features: bool = False) -> MesoNet:
    """The network of ``meso`` (None: the H-cell, alpha0 = 55 deg), two hidden layers of 16 (the shipped
    models' depth: numba compiles the step once per depth, so these are the kernels the shipped models run), weights
    and normalisation from numpy's generator (seed 7) at sizes that move the free grains by up to 1e-2 D (median 1e-3 D) per
    1e-4 of strain."""
    meso, law = h_cell(55.0) if meso is None else meso, ContactLaw()
    schema = CellSchema.from_arrays(radius=meso.radius, reference_position=meso.position,
                                    reference_cell_size=meso.cell_size, driven=meso.driven, pairs=meso.pairs,
                                    outer=meso.outer, kn=law.kn, kt=law.kt, mu=law.mu,
                                    contact_tolerance=meso.contact_tolerance)
    net = MesoNet(schema, torch.ones(schema.n_pairs, dtype=torch.bool), hidden=(16, 16), load_features=load_features)
    rng = np.random.default_rng(7)
    with torch.no_grad():
        for layer in net.mlp:
            if isinstance(layer, torch.nn.Linear):
                bound = 1.0 / np.sqrt(layer.in_features)
                layer.weight.copy_(torch.from_numpy(rng.uniform(-bound, bound, tuple(layer.weight.shape))))
                layer.bias.copy_(torch.from_numpy(rng.uniform(-bound, bound, tuple(layer.bias.shape))))
        net.mlp[-1].weight.mul_(30.0)
        net.mlp[-1].bias.copy_(torch.from_numpy(rng.normal(scale=3.0, size=tuple(net.mlp[-1].bias.shape))))
    n_in, n_free = net.feature_mean.shape[0], net.n_free
    net.set_normalisation(rng.normal(scale=0.1, size=n_in), rng.uniform(0.5, 2.0, n_in), np.zeros(n_free),
                          np.ones(n_free))
    return net


def _increments(n_cells: int = 64, n_steps: int = 12) -> list[np.ndarray]:
    """Every output of ``n_steps`` chained increments of ``n_cells`` compressed H-cells, with tangents."""
    net = _network()
    fast = FastAdvance(net)
    meso = h_cell(55.0)
    free = net.schema.free_dofs.numpy()
    rng = np.random.default_rng(11)
    squeeze = rng.uniform(5e-4, 3e-3, (n_cells, 1))
    size = meso.cell_size * (1.0 - squeeze)
    position = meso.position[free[:, 0], free[:, 1]] * (1.0 - squeeze)
    shear = np.zeros((n_cells, net.schema.n_pairs))
    out = []
    for _ in range(n_steps):
        d_eps = rng.normal(scale=1e-4, size=(n_cells, 2))
        d_eps[0] = 0.0
        step, tangent = fast.increment(size, position, shear, d_eps, with_tangent=True)
        out += [np.array(getattr(step, name)) for name in step._fields] + [tangent]
        size, position, shear = step.cell_size, step.free_position, step.shear_force
    return out


def _increments_3d(n_cells: int = 64, n_steps: int = 12) -> list[np.ndarray]:
    """Every output of ``n_steps`` chained compiled increments of ``n_cells`` compressed ten-sphere cells
    (a network with load fractions; the spatial step has no compiled tangent)."""
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    net = _network(meso, load_features=True)
    fast = FastAdvance(net)
    free = net.schema.free_dofs.numpy()
    rng = np.random.default_rng(11)
    squeeze = rng.uniform(5e-4, 3e-3, (n_cells, 1))
    size = meso.cell_size * (1.0 - squeeze)
    position = meso.position[free[:, 0], free[:, 1]] * (1.0 - squeeze)
    shear = np.zeros((n_cells, net.schema.n_pairs, 3))
    out = []
    for _ in range(n_steps):
        d_eps = rng.normal(scale=1e-4, size=(n_cells, 3))
        d_eps[0] = 0.0
        step = fast(size, position, shear, d_eps)
        out += [np.array(getattr(step, name)) for name in step._fields]
        size, position, shear = step.cell_size, step.free_position, step.shear_force
    return out


def _digest(arrays: list[np.ndarray]) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


@pytest.mark.determinism
def test_compiled_increments_are_the_same_bits_on_any_cpu():
    arrays = _increments()
    moment = arrays[3]
    assert np.isfinite(moment).all() and np.abs(moment).max() > 0.0  # loaded cells, not a trivial path
    assert _digest(arrays) == INCREMENTS_DIGEST


@pytest.mark.determinism
def test_compiled_spatial_increments_are_the_same_bits_on_any_cpu():
    arrays = _increments_3d()
    moment, shear = arrays[3], arrays[2]
    assert np.isfinite(moment).all() and np.abs(moment).max() > 0.0 and np.abs(shear).max() > 0.0
    assert _digest(arrays) == INCREMENTS_3D_DIGEST
