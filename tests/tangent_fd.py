"""Central finite differences of a cell model's step with respect to its own increment.

The reference against which every backend's consistent tangent is checked: nothing of the
backend is used but ``step`` itself.
"""

from __future__ import annotations

import numpy as np


def fd_tangent(model, state, d_eps: np.ndarray, h: float) -> np.ndarray:
    """d(S_nn, S_tt)/d(d_eps_n, d_eps_t) [N m] by central differences of ``model.step``.

    Args:
        model: a ``warp_hcell.cell_model.CellModel``.
        state: cells at the start of the increment.
        d_eps: the increment (d_eps_n, d_eps_t) [-], shape (n_cells, 2).
        h: difference step [-].

    Returns:
        Shape (n_cells, 2, 2): [:, a, b] = d S_aa / d d_eps_b.
    """
    d_eps = np.asarray(d_eps, dtype=np.float64)
    out = np.empty((d_eps.shape[0], 2, 2))
    for b in range(2):
        plus, minus = d_eps.copy(), d_eps.copy()
        plus[:, b] += h
        minus[:, b] -= h
        s_plus = model.step(state, plus)[1].moment
        s_minus = model.step(state, minus)[1].moment
        out[:, :, b] = (s_plus[:, [0, 1], [0, 1]] - s_minus[:, [0, 1], [0, 1]]) / (2.0 * h)
    return out


def relative_error(tangent: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per cell: max |tangent - reference| / max |reference| [-], shape (n_cells,)."""
    scale = np.abs(reference).max(axis=(1, 2))
    return np.abs(tangent - reference).max(axis=(1, 2)) / scale
