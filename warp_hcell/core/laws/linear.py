"""The linear contact law in numpy (``warp_hcell.core.parameters.ContactLaw``): constant
stiffnesses kn, kt [N/m], f_n = kn max(overlap, 0) (``warp_hcell.core.contact.normal_force``).

The stiffnesses come back as given (scalars or arrays), so expressions written with them keep
their bits. Interface: ``warp_hcell.core.laws``.
"""

from __future__ import annotations

from warp_hcell.core.contact import normal_force

__all__ = ["normal_force", "pair_constants", "normal_stiffness", "shear_stiffness", "move_stiffness",
           "move_stiffness_slope"]


def pair_constants(law, radius_i=None, radius_j=None):
    """(kn, kt) [N/m] of the law, the same for every pair (the radii are not needed)."""
    return law.kn, law.kt


def normal_stiffness(overlap, kn):
    """d f_n / d overlap = kn [N/m] for overlap > 0."""
    return kn


def shear_stiffness(overlap, kt):
    """Tangential stiffness kt [N/m]."""
    return kt


def move_stiffness(start_overlap, overlap, kt):
    """kt [N/m]: every move grows the spring by kt du."""
    return kt


def move_stiffness_slope(start_overlap, overlap, kt):
    """d ``move_stiffness`` / d overlap = 0."""
    return 0.0
