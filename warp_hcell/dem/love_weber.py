"""The DEM's Love-Weber sum (tension positive) and THE sign conversion at the DEM's boundary.

Inside the DEM (``warp_hcell.dem.kernels``) forces and moments are tension positive; every
quantity that leaves it is compression positive through ``to_compression_positive``.
"""

from __future__ import annotations

import numpy as np


def love_weber_tension_positive(contact_force: np.ndarray, branch: np.ndarray) -> np.ndarray:
    """DEM Love-Weber sum, tension positive: sum_c f_c (x) l_c.

    Args:
        contact_force: force on grain i by grain j [N], shape (n_cells, n_pairs, 2).
        branch: x_j - x_i [m], shape (n_cells, n_pairs, 2).

    Returns:
        (n_cells, 2, 2) [N m], local frame (n, t); negative for a compressed cell.
    """
    return np.einsum("cpa,cpb->cab", contact_force, branch)


def to_compression_positive(moment_tension_positive: np.ndarray) -> np.ndarray:
    """THE sign conversion of the DEM boundary: tension-positive -> compression-positive moment."""
    return -moment_tension_positive
