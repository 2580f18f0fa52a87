"""The contact laws of the package, written once for numpy and numba.

Linear normal spring without tension, incremental tangential spring with a Coulomb cap:

    f_n = kn max(overlap, 0),  f_s = clip(f_s,old + kt du, -mu f_n, +mu f_n),

with overlap = r_i + r_j - norm(x_j - x_i) [m] (negative: a gap) and du the tangential relative
displacement of the step [m]. The trial force f_s,old + kt du decides the sliding direction.
Each law holds its stiffnesses in its own module (``warp_hcell.core.laws``: ``linear``,
``hertz_mindlin``), found by the law's name; ``PairLaw`` evaluates any of them for a batch of
pairs (``pair_law``), with the cap above.

Every function works elementwise on numpy arrays and, compiled by ``numba.njit``, on scalars
inside numba kernels (``training.inference``); the results are bit for bit the same. The Warp
kernels (``warp_hcell.dem.contact``) and the torch cell physics (``training.cell_physics``)
hold the same law in their languages; ``tests/test_contact_law_conformance.py`` drives every
copy with the same contacts.

Units: overlaps and displacements [m], stiffnesses [N/m], forces [N], mu [-].
"""

from __future__ import annotations

import numpy as np

from warp_hcell.core.laws import numpy_law
from warp_hcell.core.parameters import ContactLaw

CAP_SLACK = 1e-12
"""Relative excess of a spatial spring over mu f_n that the vector cap leaves alone [-]: the 3D cap
rescales the spring to mu f_n (to rounding), so a capped spring is capped again only if it grew;
re-evaluating a capped state then gives the same forces bit for bit."""
OPEN, STICK, SLIDE = 0, 1, 2
"""Contact regimes: out of contact, sticking, sliding (tangential force at the Coulomb cap)."""


def normal_force(overlap, kn):
    """Normal (repulsive) force f_n = kn max(overlap, 0) [N], never tension."""
    return kn * np.maximum(overlap, 0.0)


def coulomb_cap(trial, normal, mu):
    """The trial tangential force [N] capped at mu f_n with its own sign: clip(trial, -mu f_n, mu f_n)."""
    cap = mu * normal
    return np.minimum(np.maximum(trial, -cap), cap)


def tangential_force(shear_force, shear_increment, normal, kt, mu):
    """New tangential force [N] of a contact: the spring f_s grows by kt du, then ``coulomb_cap``."""
    return coulomb_cap(shear_force + kt * shear_increment, normal, mu)


def regime(normal, shear, mu):
    """``SLIDE`` where a loaded contact's tangential force is at its cap (abs(f_s) >= mu f_n), else
    ``STICK``; for contacts within the contact tolerance (``OPEN`` is the caller's test)."""
    return np.where((normal > 0.0) & (np.abs(shear) >= mu * normal), SLIDE, STICK)


def reduced_radius_root(radius_i, radius_j):
    """sqrt(R*) [m^0.5] of pairs of radii r_i, r_j [m] (arrays broadcast), R* = r_i r_j / (r_i + r_j)."""
    return np.sqrt(radius_i * radius_j / (radius_i + radius_j))


class PairLaw:
    """A contact law evaluated for a batch of pairs (numpy, elementwise over overlaps), by the law's
    module (``warp_hcell.core.laws``) with its two pair constants ``kn``, ``kt``.

    ``normal(overlap)`` [N], ``normal_stiffness(overlap)`` d f_n / d overlap [N/m] and
    ``shear_stiffness(overlap)`` kt [N/m]. The linear law returns its kn and kt as given
    (scalars or arrays), so expressions written with them keep their bits.
    """

    def __init__(self, name: str, kn, kt) -> None:
        self.name = name
        self.kn = kn
        """Linear: kn [N/m]; Hertz-Mindlin: kh [N/m^1.5]."""
        self.kt = kt
        """Linear: kt [N/m]; Hertz-Mindlin: ks [N/m^1.5]."""
        self._law = numpy_law(name)

    @property
    def linear(self) -> bool:
        """True for the linear law (constant stiffnesses)."""
        return self.name == ContactLaw.name

    def normal(self, overlap):
        """Normal force [N] at ``overlap`` [m], never tension."""
        return self._law.normal_force(overlap, self.kn)

    def normal_stiffness(self, overlap):
        """d f_n / d overlap [N/m] for overlap > 0 (the linear law: kn)."""
        return self._law.normal_stiffness(overlap, self.kn)

    def shear_stiffness(self, overlap):
        """Tangential stiffness kt [N/m] at ``overlap`` (the linear law: kt)."""
        return self._law.shear_stiffness(overlap, self.kt)

    def move_stiffness(self, start_overlap, overlap):
        """Stiffness [N/m] by which a move from ``start_overlap`` to ``overlap`` grows the spring
        (the linear law: kt; Hertz-Mindlin: the mean Mindlin stiffness of the move)."""
        return self._law.move_stiffness(start_overlap, overlap, self.kt)

    def move_stiffness_slope(self, start_overlap, overlap):
        """d ``move_stiffness`` / d overlap [N/m^2] (the linear law: 0)."""
        return self._law.move_stiffness_slope(start_overlap, overlap, self.kt)


def pair_law(law, radius_i=None, radius_j=None) -> PairLaw:
    """``PairLaw`` of a contact-law declaration (``warp_hcell.core.parameters``) for pairs of radii
    r_i, r_j [m] (arrays broadcast; the linear law ignores them)."""
    return PairLaw(law.name, *numpy_law(law.name).pair_constants(law, radius_i, radius_j))
