"""A distribution of initial opening angles in one material point (a spread of alpha0).

A material point whose cells do not all start at one opening angle: its cells fall in
``N_NODES`` families, family j at alpha0 + spread * x_j with weight g_j, (x_j, g_j) the
Gauss-Legendre nodes and weights of the uniform distribution on [-1, 1] (g_j summing to 1). So
``spread`` [deg] is the half-width of a uniform distribution of opening angles about the point's
alpha0 [deg], and spread = 0 is the single opening angle of the plain H-model. Each family is the
whole orientation rule of the point (``replicate``): cell j * N + k is orientation k of family j, of
weight g_j w_k. The homogenisation is the Love-Weber sum over every cell of the point,
sigma = sum_j g_j sum_k w_k R_k S_jk R_k^T / (V0 J), V0 = sum_j g_j sum_k w_k V_jk: a point of
spread s is the families' moments over their volumes, i.e. the volume-weighted mean
sum_j g_j V0_j sigma_j / sum_j g_j V0_j of single-alpha0 points under the same strain.

A run of one material point (``hmodel triaxial --posterior`` of a calibration with a spread) gives
its cell model per-cell opening angles (``cell_alpha0``) and ``FAMILIES_ATTRIBUTE``.

The ten-sphere cell needs every opening angle >= ``ALPHA_MIN_3D_DEG``: the distribution's lowest,
alpha0 - spread, must be (``check``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from homogenization.material.orientation import OrientationSet
from warp_hcell.core.parameters import ALPHA_MIN_3D_DEG

N_NODES = 3
"""Families of opening angles per material point (Gauss-Legendre nodes of the uniform distribution) [-]."""
NAME = "alpha0_spread"
"""The spread's parameter name in a calibration (posterior.json, --params) [deg]."""
FAMILIES_ATTRIBUTE = "alpha0_families"
"""Attribute (True) of a cell model whose cells carry a point's ``N_NODES`` families of opening angles for
one orientation rule (``cell_alpha0`` of one point): ``element_test.points.material_points`` then
orients them by ``replicate`` of the rule it builds."""


def nodes() -> tuple[np.ndarray, np.ndarray]:
    """The families' offsets x_j in units of the spread, shape (N_NODES,) in (-1, 1), and their
    weights g_j [-], summing to 1 (Gauss-Legendre on [-1, 1], weights halved)."""
    x, w = np.polynomial.legendre.leggauss(N_NODES)
    return x, 0.5 * w


def check(alpha0_deg: np.ndarray | float, spread_deg: np.ndarray | float) -> None:
    """ValueError (one line) for a spread < 0 or an opening alpha0 - spread below ``ALPHA_MIN_3D_DEG``."""
    alpha0, spread = np.broadcast_arrays(np.asarray(alpha0_deg, dtype=np.float64),
                                         np.asarray(spread_deg, dtype=np.float64))
    bad = ~(spread >= 0.0)
    if bad.any():
        raise ValueError(f"alpha0_spread = {float(spread[bad].flat[0]):g} deg must be >= 0")
    low = ~(alpha0 - spread >= ALPHA_MIN_3D_DEG)
    if low.any():
        i = np.flatnonzero(low.ravel())[0]
        raise ValueError(f"alpha0 - alpha0_spread = {float(alpha0.ravel()[i]):g} - {float(spread.ravel()[i]):g} deg is "
                         f"below {ALPHA_MIN_3D_DEG:g} deg, the ten-sphere cell's smallest opening angle")


def feasible(alpha0_deg: np.ndarray, spread_deg: np.ndarray) -> np.ndarray:
    """Whether each (alpha0, spread) pair is allowed (``check``), shape of the broadcast."""
    alpha0, spread = np.asarray(alpha0_deg, dtype=np.float64), np.asarray(spread_deg, dtype=np.float64)
    return (spread >= 0.0) & (alpha0 - spread >= ALPHA_MIN_3D_DEG)


def replicate(orient: OrientationSet) -> OrientationSet:
    """The orientation set of a point with ``N_NODES`` families: ``orient``'s N cells once per family,
    family-major, weights g_j w_k (module docstring); of the same class, arrays read-only."""
    _, g = nodes()
    n = orient.n_cells
    arrays = {"frames": np.concatenate([orient.frames] * N_NODES, axis=0)}
    if hasattr(orient, "theta"):
        arrays["theta"] = np.concatenate([orient.theta] * N_NODES, axis=0)
    arrays["weights"] = (g[:, None] * orient.weights[None, :]).reshape(-1)
    arrays["localisation"] = np.concatenate([orient.localisation] * N_NODES, axis=0)
    per_cell = orient.averaging.reshape(orient.averaging.shape[0], n, -1)
    arrays["averaging"] = np.concatenate([gj * per_cell for gj in g], axis=1).reshape(orient.averaging.shape[0], -1)
    for a in arrays.values():
        a.flags.writeable = False
    return replace(orient, **arrays)


def cell_alpha0(alpha0_deg: np.ndarray, spread_deg: np.ndarray, n_orientations: int) -> np.ndarray:
    """Opening angle [deg] of every cell of n points (point-major, then family, then orientation),
    shape (n * N_NODES * n_orientations,), of the points' alpha0 and spread [deg], shape (n,)."""
    x, _ = nodes()
    alpha0 = np.asarray(alpha0_deg, dtype=np.float64)[:, None]
    spread = np.asarray(spread_deg, dtype=np.float64)[:, None]
    return np.repeat(alpha0 + spread * x[None, :], int(n_orientations), axis=1).reshape(-1)
