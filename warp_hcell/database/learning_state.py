"""The generic learning state of a cell, evaluated with numpy: the derived features.

A learning state (``warp_hcell.core.contract.StateSchema``) is the cell size, the free-DOF
coordinates and the per-pair tangential spring forces. ``evaluate`` applies the contact law
of the DEM (``warp_hcell.core.contact``) at those positions with no displacement: contact flags,
normal forces, the tangential forces after the Coulomb cap (zero out of contact), the net
force on each free DOF, the Love-Weber moment and the area. Evaluated on a state the DEM
produced, it reproduces the DEM's own forces; on a perturbed state it gives the unbalanced
forces the DEM starts relaxing from.

Conventions: local frame index 0 = n, 1 = t (2D) or 1 = t1, 2 = t2 (3D). Forces are the
DEM's: for pair (i, j), ``u = (x_j - x_i) / |x_j - x_i|``; in 2D w = (-u_t, u_n) and the force
on grain i by grain j is -f_n u + f_s w (f_n >= 0); in 3D the spring is a vector f_s in the
tangent plane and the force is -f_n u + f_s, capped at mu f_n along its own direction. The
moment is returned compression positive; ``area`` is V_cell (the volume of a spatial cell).
"""

from __future__ import annotations

import numpy as np

from warp_hcell.core.contact import normal_force
from warp_hcell.core.contract import StateSchema
from warp_hcell.database.dimensions import DIMENSIONS
from warp_hcell.dem.love_weber import love_weber_tension_positive, to_compression_positive
from warp_hcell.mesostructures.mesostructure import cell_measure
from warp_hcell.core.parameters import ContactLaw

def positions(schema: StateSchema, cell_size: np.ndarray, free_position: np.ndarray) -> np.ndarray:
    """All grain centres [m], shape (n, n_grains, dim): driven DOFs at x_ref * l / l_ref.

    Args:
        cell_size: (l1, l2[, l3]) [m], shape (n, dim).
        free_position: free-DOF coordinates [m], shape (n, n_free), order ``schema.free_dofs``.
    """
    cell_size = np.asarray(cell_size, dtype=np.float64)
    x = schema.reference_position[None] * (cell_size / schema.reference_cell_size)[:, None, :]
    x[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]] = free_position
    return x


def free_coordinates(schema: StateSchema, position: np.ndarray) -> np.ndarray:
    """The free-DOF coordinates [m] of grain centres ``position`` (n, n_grains, dim): (n, n_free)."""
    return np.ascontiguousarray(position[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]])


def pair_normal_forces(schema: StateSchema, x: np.ndarray, contact_law: ContactLaw, contact_tolerance: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Branch vectors x_j - x_i [m] (n, n_pairs, dim), distances [m] (n, n_pairs), contact flags (gap within
    ``contact_tolerance`` (r_i + r_j)) bool (n, n_pairs) and normal forces f_n >= 0 [N] (n, n_pairs) of every
    pair of grain centres ``x`` (n, n_grains, dim) (``positions``): the part of ``evaluate`` that needs no springs."""
    pi, pj = schema.pairs[:, 0], schema.pairs[:, 1]
    rsum = schema.radius[pi] + schema.radius[pj]
    widen = 1.0 + contact_tolerance
    cut2 = (rsum * widen) * (rsum * widen)
    b = x[:, pj] - x[:, pi]
    dist2 = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1]
    for axis in range(2, schema.dim):
        dist2 = dist2 + b[..., axis] * b[..., axis]
    touching = dist2 <= cut2
    dist = np.sqrt(dist2)
    return b, dist, touching, np.where(touching, normal_force(rsum - dist, contact_law.kn), 0.0)


def evaluate(schema: StateSchema, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
             contact_law: ContactLaw, contact_tolerance: float) -> dict[str, np.ndarray]:
    """Contact-law evaluation of a learning state (module docstring), vectorised over cells.

    Args:
        cell_size: (n, dim) [m]; free_position: (n, n_free) [m]; shear_force: (n, ``*schema.shear_shape``) [N].
        contact_law: stiffnesses and friction of the DEM.
        contact_tolerance: gap, as a fraction of r_i + r_j, that still counts as a contact [-].

    Returns:
        ``position`` (n, n_grains, dim) [m]; ``contact`` (n, n_pairs) int8; ``normal_force``
        (n, n_pairs) and ``shear_force`` (n, ``*shear_shape``) [N]; ``contact_force``
        (n, n_pairs, dim) [N] on grain i; ``unbalanced`` (n, n_free) [N]; ``moment``
        (n, dim, dim) [N m] compression positive; ``area`` (n,) [m^2] (3D: volume [m^3]).
    """
    x = positions(schema, cell_size, free_position)
    pi, pj = schema.pairs[:, 0], schema.pairs[:, 1]
    b, dist, touching, normal = pair_normal_forces(schema, x, contact_law, contact_tolerance)
    u = b / np.where(dist > 0.0, dist, 1.0)[..., None]
    shear, force = DIMENSIONS[schema.dim].pair_forces(shear_force, normal, u, touching, contact_law.mu)
    net = np.zeros_like(x)
    for p in range(schema.n_pairs):  # pair order fixed: the DEM's summation order
        net[:, pi[p]] += force[:, p]
        net[:, pj[p]] -= force[:, p]
    moment = to_compression_positive(love_weber_tension_positive(force, b))
    return {"position": x, "contact": touching.astype(np.int8), "normal_force": normal, "shear_force": shear,
            "contact_force": force, "unbalanced": net[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]],
            "moment": moment, "area": cell_measure(x, schema.outer)}
