"""The generic learning state of a cell, evaluated with numpy: derived features, H-cell observables.

A learning state (``warp_hcell.core.contract.StateSchema``) is the cell size, the free-DOF
coordinates and the per-pair tangential spring forces. ``evaluate`` applies the contact law
of the DEM (``warp_hcell.dem.kernels``) at those positions with no displacement: contact flags,
normal forces, the tangential forces after the Coulomb cap (zero out of contact), the net
force on each free DOF, the Love-Weber moment and the area. Evaluated on a state the DEM
produced, it reproduces the DEM's own forces; on a perturbed state it gives the unbalanced
forces the DEM starts relaxing from.

``hcell_observables`` measures alpha, d1, d2, N1, N2, T1 at the reference contacts of a
mesostructure carrying H-cell labels (``Mesostructure.h_reference_pairs``); nothing else here
knows the H-cell.

Conventions: local frame index 0 = n, 1 = t. Forces are the DEM's: for pair (i, j),
``u = (x_j - x_i) / |x_j - x_i|``, w = (-u_t, u_n), the force on grain i by grain j is
-f_n u + f_s w (f_n >= 0). The moment is returned compression positive.
"""

from __future__ import annotations

import numpy as np

from warp_hcell.core.contract import StateSchema
from warp_hcell.mesostructures.mesostructure import Mesostructure, polygon_area
from warp_hcell.core.parameters import ContactLaw

def positions(schema: StateSchema, cell_size: np.ndarray, free_position: np.ndarray) -> np.ndarray:
    """All grain centres [m], shape (n, n_grains, 2): driven DOFs at x_ref * l / l_ref.

    Args:
        cell_size: (l1, l2) [m], shape (n, 2).
        free_position: free-DOF coordinates [m], shape (n, n_free), order ``schema.free_dofs``.
    """
    cell_size = np.asarray(cell_size, dtype=np.float64)
    x = schema.reference_position[None] * (cell_size / schema.reference_cell_size)[:, None, :]
    x[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]] = free_position
    return x


def free_coordinates(schema: StateSchema, position: np.ndarray) -> np.ndarray:
    """The free-DOF coordinates [m] of grain centres ``position`` (n, n_grains, 2): (n, n_free)."""
    return np.ascontiguousarray(position[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]])


def evaluate(schema: StateSchema, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
             contact_law: ContactLaw, contact_tolerance: float) -> dict[str, np.ndarray]:
    """Contact-law evaluation of a learning state (module docstring), vectorised over cells.

    Args:
        cell_size: (n, 2) [m]; free_position: (n, n_free) [m]; shear_force: (n, n_pairs) [N].
        contact_law: stiffnesses and friction of the DEM.
        contact_tolerance: gap, as a fraction of r_i + r_j, that still counts as a contact [-].

    Returns:
        ``position`` (n, n_grains, 2) [m]; ``contact`` (n, n_pairs) int8; ``normal_force`` and
        ``shear_force`` (n, n_pairs) [N]; ``contact_force`` (n, n_pairs, 2) [N] on grain i;
        ``unbalanced`` (n, n_free) [N]; ``moment`` (n, 2, 2) [N m] compression positive;
        ``area`` (n,) [m^2].
    """
    x = positions(schema, cell_size, free_position)
    pi, pj = schema.pairs[:, 0], schema.pairs[:, 1]
    rsum = schema.radius[pi] + schema.radius[pj]
    widen = 1.0 + contact_tolerance
    cut2 = (rsum * widen) * (rsum * widen)
    b = x[:, pj] - x[:, pi]
    dist2 = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1]
    touching = dist2 <= cut2
    dist = np.sqrt(dist2)
    u = b / np.where(dist > 0.0, dist, 1.0)[..., None]
    normal = np.where(touching, contact_law.kn * np.maximum(rsum - dist, 0.0), 0.0)
    cap = contact_law.mu * normal
    shear = np.where(touching, np.clip(np.asarray(shear_force, dtype=np.float64), -cap, cap), 0.0)
    force = np.stack([-normal * u[..., 0] - shear * u[..., 1], -normal * u[..., 1] + shear * u[..., 0]], axis=-1)
    net = np.zeros_like(x)
    for p in range(schema.n_pairs):  # pair order fixed: the DEM's summation order
        net[:, pi[p]] += force[:, p]
        net[:, pj[p]] -= force[:, p]
    moment = to_compression_positive(love_weber_tension_positive(force, b))
    return {"position": x, "contact": touching.astype(np.int8), "normal_force": normal, "shear_force": shear,
            "contact_force": force, "unbalanced": net[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]],
            "moment": moment, "area": polygon_area(x, schema.outer)}


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


HCELL_OBSERVABLES = ("alpha_deg", "d1", "d2", "N1", "N2", "T1")
"""H-cell observables stored for reports (group ``hcell`` of the database)."""


def hcell_observables(meso: Mesostructure, position: np.ndarray, normal_force: np.ndarray,
                      shear_force: np.ndarray, contact: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """alpha [deg], d1, d2 [m], N1, N2, T1 [N] at the reference contacts 1-2 and 2-3.

    Args:
        meso: a mesostructure with H-cell labels (``meso.is_h_cell``).
        position: (n, n_grains, 2) [m]; normal_force, shear_force: (n, n_pairs) [N].
        contact: optional contact flags (n, n_pairs); with them also ``closed1, closed2``.

    Returns:
        Each (n,); N compression positive, T1 > 0 resists opening (the DEM's spring force);
        ``closed1, closed2`` bool.
    """
    reference = meso.h_reference_pairs
    if reference is None:
        raise ValueError(f"mesostructure {meso.name!r} has no H-cell labels")
    p1, p2 = reference
    (i1, j1), (i2, j2) = meso.pairs[p1], meso.pairs[p2]
    b1 = position[:, j1] - position[:, i1]
    b2 = position[:, j2] - position[:, i2]
    obs = {"alpha_deg": np.degrees(np.arctan2(-b1[:, 1], -b1[:, 0])), "d1": np.hypot(b1[:, 0], b1[:, 1]),
           "d2": np.hypot(b2[:, 0], b2[:, 1]), "N1": normal_force[:, p1].copy(), "N2": normal_force[:, p2].copy(),
           "T1": shear_force[:, p1].copy()}
    if contact is not None:
        obs.update(closed1=contact[:, p1] == 1, closed2=contact[:, p2] == 1)
    return obs
