"""The Hertz-Mindlin contact law in the DEM kernels (Warp, float64), as ``warp_hcell.core.laws.hertz_mindlin``.

The kernel takes (4/3) E* and 8 G* [Pa] (``kernel_constants``) and scales them by sqrt(R*) of each
pair (``pair_scale``, R* = r_i r_j / (r_i + r_j)) into the pair constants kh and ks [N/m^1.5]:
f_n = kh delta sqrt(delta), the spring grows by the mean Mindlin stiffness of the move from its
start overlap (``mindlin_move_stiffness``) times the displacement, delta = max(overlap, 0); the cap
and the regimes are the linear law's. Interface: ``warp_hcell.dem.laws``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_hcell.core.parameters import HERTZ_DT_OVERLAP, HertzMindlinLaw
from warp_hcell.dem.contact import capped_spring, carried_spring
from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def pair_scale(r_i: wp.float64, r_j: wp.float64, r_sum: wp.float64):
    """sqrt(R*) [m^0.5] of a pair of radii r_i, r_j [m], r_sum = r_i + r_j."""
    return wp.sqrt(r_i * r_j / r_sum)


@wp.func
def pair_constant(k: wp.float64, scale: wp.float64):
    """The pair constant k sqrt(R*) [N/m^1.5] of the kernel's modulus k [Pa]."""
    return k * scale


@wp.func
def normal_force(overlap: wp.float64, kh: wp.float64):
    """Hertz normal force kh delta sqrt(delta) [N], delta = max(overlap, 0) [m]; kh [N/m^1.5]."""
    zero = wp.float64(0.0)
    delta = wp.where(overlap > zero, overlap, zero)
    return kh * (delta * wp.sqrt(delta))


@wp.func
def mindlin_move_stiffness(start_overlap: wp.float64, overlap: wp.float64, ks: wp.float64):
    """Mean Mindlin stiffness [N/m] of a move from ``start_overlap`` to ``overlap`` [m]:
    (2/3) ks (a^2 + a b + b^2) / (a + b), a = sqrt(max(overlap, 0)), b = sqrt(max(start_overlap, 0)); 0
    where both are <= 0."""
    zero = wp.float64(0.0)
    a = wp.sqrt(wp.where(overlap > zero, overlap, zero))
    b = wp.sqrt(wp.where(start_overlap > zero, start_overlap, zero))
    total = a + b
    return wp.where(total > zero,
                    (wp.float64(2.0) / wp.float64(3.0)) * ks * ((a * a + a * b + b * b) / wp.where(total > zero, total,
                                                                                                  wp.float64(1.0))),
                    zero)


@wp.func
def contact_law_3d(
    overlap: wp.float64,
    start_overlap: wp.float64,
    shear_increment: wp.vec3d,
    carried: wp.vec3d,
    kh: wp.float64,
    ks: wp.float64,
    mu: wp.float64,
):
    """``warp_hcell.dem.contact.contact_law_3d`` of the Hertz-Mindlin law: f_n = kh delta sqrt(delta), the
    spring grows by ``mindlin_move_stiffness(start_overlap, overlap, ks)`` times ``shear_increment``
    (``start_overlap`` [m]: the overlap before the move), cap mu f_n along the trial force; kh, ks
    [N/m^1.5] (``warp_hcell.core.laws.hertz_mindlin.pair_constants``).

    Returns:
        (normal force >= 0 [N], new tangential force vector [N], regime: 1 sticking, 2 sliding).
    """
    return capped_spring(normal_force(overlap, kh), carried + mindlin_move_stiffness(start_overlap, overlap, ks)
                         * shear_increment, mu)


@wp.func
def spatial_contact(u: wp.vec3d, rel: wp.vec3d, overlap: wp.float64, spring: wp.vec3d, kh: wp.float64,
                    ks: wp.float64, mu: wp.float64):
    """One spatial pair within reach (``warp_hcell.dem.pairs``), kh, ks [N/m^1.5] the pair's constants;
    the move started at the overlap overlap + rel . u (it opened the pair by rel . u, to first order)."""
    opening = wp.dot(rel, u)
    du = rel - opening * u
    return contact_law_3d(overlap, overlap + opening, du, carried_spring(spring, u), kh, ks, mu)


def kernel_constants(law: HertzMindlinLaw) -> tuple[float, float, float]:
    """((4/3) E*, 8 G* [Pa], mu [-]): the kernel scales the moduli by sqrt(R*) per pair."""
    return law.normal_modulus, law.shear_stiffness_modulus, law.mu


def reference_stiffness(law: HertzMindlinLaw, radius: np.ndarray) -> np.ndarray:
    """The tangent stiffness [N/m] at the overlap HERTZ_DT_OVERLAP (2 r) of the cell's smallest grain
    radius r, shape (n_cells,) (``radius``: (n_cells, n_grains) [m])."""
    smallest = radius.min(axis=1)
    return 1.5 * law.normal_modulus * np.sqrt(0.5 * smallest * (HERTZ_DT_OVERLAP * 2.0 * smallest))
