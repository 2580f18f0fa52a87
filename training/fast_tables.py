"""The records the compiled meso-ANN increment takes and fills: cell tables, physics, scratch and results.

NamedTuples of numpy arrays and floats, so that the numba kernels (``training.fast_cells``,
``training.fast_features``, ``training.fast_increment``, ``training.fast_step3d``) and the precompiled
step (``training.precompiled``) take them whole; importing this module imports no numba.
Every array is cells LAST (one cell a vector lane, nothing reduced across cells). Sign convention:
compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from typing import NamedTuple

import numpy as np


class CellTables(NamedTuple):
    """The mesostructure's topology: frac = x_ref / l_ref (n_grains, 2) [-]; free_dofs (n_free, 2)
    (grain, axis); free_slot (n_grains, 2), the rank of DOF (g, a) among the free DOFs, -1 if driven;
    pairs (n_pairs, 2); radius (n_grains,) [m]; outer (n_outer,) polygon of the area; active_slot
    (n_pairs,), the rank of pair p among the network's active pairs, -1 if inactive."""

    frac: np.ndarray
    free_dofs: np.ndarray
    free_slot: np.ndarray
    pairs: np.ndarray
    radius: np.ndarray
    outer: np.ndarray
    active_slot: np.ndarray


class Physics(NamedTuple):
    """Contact law and scales: diameter D [m], kn, kt [N/m], mu [-], contact tolerance tol [-], the
    gap clip of the features [D], the compliance scale of the relaxation term and the relaxation ramp
    [-] (``training.network``)."""

    diameter: float
    kn: float
    kt: float
    mu: float
    tol: float
    gap_clip: float
    compliance_scale: float
    ramp: float


class Normalisation(NamedTuple):
    """The network's z-scores: feature_mean, feature_std (n_features,); rate_mean, rate_std (n_free,)
    [D per unit strain]."""

    feature_mean: np.ndarray
    feature_std: np.ndarray
    rate_mean: np.ndarray
    rate_std: np.ndarray


class Before(NamedTuple):
    """What ``fast_features.features`` leaves of the state before the increment: feats (n_features, n)
    float32 (planar cells in ``FastAdvance``: ``training.mlp.padded_cells(n)`` columns, the
    others scratch), m = norm(d_eps) (n,), unbalanced (n_free, n) [N], old_branch (n_pairs, 2, n) [m],
    old_contact (n_pairs, n) bool, old_fn (n_pairs, n) [N]."""

    feats: np.ndarray
    m: np.ndarray
    unbalanced: np.ndarray
    old_branch: np.ndarray
    old_contact: np.ndarray
    old_fn: np.ndarray


class Advanced(NamedTuple):
    """What ``fast_increment.advance`` writes: the new state new_size (2, n), new_free (n_free, n),
    new_shear (n_pairs, n); the compression-positive moment (n, 2, 2) [N m] (cells FIRST), the area
    (n,) [m^2]; per-cell flags (bool (n,)): capped (a trial tangential force exceeded mu f_n), opened
    (a pair carrying a normal force opened), mechanism (zero moment), ramped (norm(d_eps) < ramp
    scaled the relaxation down); n_held (n,) int64, the grains held at rest; held_dof (n_free, n)
    bool, the free DOFs of those grains."""

    new_size: np.ndarray
    new_free: np.ndarray
    new_shear: np.ndarray
    moment: np.ndarray
    area: np.ndarray
    capped: np.ndarray
    opened: np.ndarray
    mechanism: np.ndarray
    ramped: np.ndarray
    n_held: np.ndarray
    held_dof: np.ndarray
