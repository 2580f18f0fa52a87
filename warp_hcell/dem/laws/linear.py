"""The linear contact law in the DEM kernels (Warp, float64): the kernel's kn and kt [N/m] are every
pair's (``warp_hcell.dem.contact``: ``normal_force``, ``contact_law_3d``). Interface:
``warp_hcell.dem.laws``.
"""

from __future__ import annotations

import warp as wp

from warp_hcell.core.parameters import ContactLaw
from warp_hcell.dem.contact import carried_spring, contact_law_3d, normal_force
from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

__all__ = ["normal_force", "pair_scale", "pair_constant", "spatial_contact", "kernel_constants",
           "reference_stiffness"]


@wp.func
def pair_scale(r_i: wp.float64, r_j: wp.float64, r_sum: wp.float64):
    """1: the linear law's constants do not depend on the radii."""
    return wp.float64(1.0)


@wp.func
def pair_constant(k: wp.float64, scale: wp.float64):
    """The kernel's constant k [N/m] as it is."""
    return k


@wp.func
def spatial_contact(u: wp.vec3d, rel: wp.vec3d, overlap: wp.float64, spring: wp.vec3d, kn: wp.float64,
                    kt: wp.float64, mu: wp.float64):
    """One spatial pair within reach (``warp_hcell.dem.pairs``): the spring carried into the tangent
    plane of u, then grown by kt times the tangential part of rel; returns (f_n [N], new spring
    vector [N], regime: 1 sticking, 2 sliding)."""
    du = rel - wp.dot(rel, u) * u
    return contact_law_3d(overlap, du, carried_spring(spring, u), kn, kt, mu)


def kernel_constants(law: ContactLaw) -> tuple[float, float, float]:
    """(kn, kt [N/m], mu [-]) of the law."""
    return law.kn, law.kt, law.mu


def reference_stiffness(law: ContactLaw, radius) -> float:
    """kn [N/m]: the stiffness of every contact."""
    return law.kn
