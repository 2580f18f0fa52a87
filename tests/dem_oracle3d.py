"""Numpy engine of the 3D cell step (``warp_hcell.dem.kernels3d``): the reference the Warp kernel must equal bit for bit.

The stepping is ``dem_oracle.step_cells``, shared with the planar oracle; here the spatial pairs
and the volume. The same floating-point operations in the same order as the kernel (sums over
grains, axes and pairs in index order; Warp's dot, length and cross written out as the kernel
evaluates them).
"""

from __future__ import annotations

import numpy as np
from dem_oracle import step_cells


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def step(arrays: dict, d_eps: np.ndarray, *, pairs: np.ndarray, driven: np.ndarray, faces: np.ndarray,
         law, settings) -> dict[str, np.ndarray]:
    """One increment of every cell (``dem_oracle.step_cells`` with the spatial pairs and volume).

    Args:
        arrays: ``radius`` (n, g), ``inv_mass`` (n, g), ``reference_position`` (n, g, 3),
            ``reference_cell_size`` (n, 3), ``dt`` (n,), ``force_floor`` (n,), and the state
            ``position`` (n, g, 3), ``velocity`` (n, g, 3), ``shear_force`` (n, p, 3), ``cell_size`` (n, 3).
        d_eps: (n, 3) [-]; pairs (p, 2), driven (g, 3) bool, faces (f, 3): the topology.
        law: ``ContactLaw``; settings: ``DemSettings``.

    Returns:
        The kernel's outputs: position, velocity, shear_force, contact_force, contact, cell_size,
        moment (tension positive), volume, substeps, converged.
    """
    return step_cells(arrays, d_eps, pairs=pairs, driven=driven, law=law, settings=settings, inner=_dot,
                      pair_law=_pair_law, pair_force=lambda fs, normal, u: fs - normal[..., None] * u,
                      cell_volume=lambda x: _volume(x, faces))


def _pair_law(old: np.ndarray, overlap: np.ndarray, u: np.ndarray, rel: np.ndarray, on: np.ndarray, law):
    du = rel - _dot(rel, u)[..., None] * u
    projected = old - _dot(old, u)[..., None] * u
    before2, after2 = _dot(old, old), _dot(projected, projected)
    carried = np.where((after2 > 0.0)[..., None],
                       projected * np.sqrt(before2 / np.where(after2 > 0.0, after2, 1.0))[..., None], projected)
    normal = law.kn * np.where(overlap > 0.0, overlap, 0.0)
    trial = carried + law.kt * du
    cap = law.mu * normal
    size = np.sqrt(_dot(trial, trial))
    shear = np.where((size > cap)[..., None], trial * (cap / np.where(size > 0.0, size, 1.0))[..., None], trial)
    shear = np.where(on[..., None], shear, 0.0)
    normal = np.where(on, normal, 0.0)
    regime = np.where(on, np.where((normal > 0.0) & (size >= cap), 2.0, 1.0), 0.0)
    return shear, normal, regime, np.where(on[..., None], shear - normal[..., None] * u, 0.0)


def _volume(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    six_volume = np.zeros(x.shape[0])
    for fa, fb, fc in faces:
        six_volume = six_volume + _dot(x[:, fa], _cross(x[:, fb], x[:, fc]))
    return np.abs(six_volume) / 6.0
