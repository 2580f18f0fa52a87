"""The contact laws of the package, written once for numpy and numba.

Linear normal spring without tension, incremental tangential spring with a Coulomb cap:

    f_n = kn max(overlap, 0),  f_s = clip(f_s,old + kt du, -mu f_n, +mu f_n),

with overlap = r_i + r_j - norm(x_j - x_i) [m] (negative: a gap) and du the tangential relative
displacement of the step [m]. The trial force f_s,old + kt du decides the sliding direction.
The Hertz-Mindlin law (``warp_hcell.core.parameters.HertzMindlinLaw``) replaces the two
stiffnesses by functions of the overlap: f_n = kh delta sqrt(delta) and kt = ks sqrt(delta),
delta = max(overlap, 0), with the pair constants kh = (4/3) E* sqrt(R*) and ks = 8 G* sqrt(R*)
[N/m^1.5] (``hertz_pair_constants``); the cap is the same. A move from overlap delta0 to delta1
grows the spring by the mean of kt over the move (delta linear in the move) times du:

    kt(delta0, delta1) = (2/3) ks (delta1 + sqrt(delta0 delta1) + delta0) / (sqrt(delta1) + sqrt(delta0))

(= ks sqrt(delta) where delta0 = delta1; exact for a contact that closes within the move), in
every runtime (``mindlin_move_stiffness``). ``pair_law`` evaluates either law for a batch of pairs.

Every function works elementwise on numpy arrays and, compiled by ``numba.njit``, on scalars
inside numba kernels (``training.inference``); the results are bit for bit the same. The Warp
kernels (``warp_hcell.dem.contact``) and the torch cell physics (``training.cell_physics``)
hold the same law in their languages; ``tests/test_contact_law_conformance.py`` drives every
copy with the same contacts.

Units: overlaps and displacements [m], stiffnesses [N/m], forces [N], mu [-].
"""

from __future__ import annotations

import numpy as np

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


def hertz_normal_force(overlap, kh):
    """Hertz normal force f_n = kh delta sqrt(delta) [N], delta = max(overlap, 0) [m]; kh [N/m^1.5]."""
    delta = np.maximum(overlap, 0.0)
    return kh * (delta * np.sqrt(delta))


def hertz_normal_stiffness(overlap, kh):
    """Tangent normal stiffness d f_n / d overlap = 1.5 kh sqrt(delta) [N/m] (0 without overlap)."""
    return 1.5 * kh * np.sqrt(np.maximum(overlap, 0.0))


def mindlin_shear_stiffness(overlap, ks):
    """Mindlin tangential stiffness kt = ks sqrt(delta) [N/m], delta = max(overlap, 0); ks [N/m^1.5]."""
    return ks * np.sqrt(np.maximum(overlap, 0.0))


def mindlin_move_stiffness(start_overlap, overlap, ks):
    """Mean Mindlin stiffness [N/m] of a move from ``start_overlap`` to ``overlap`` [m] (module
    docstring); 0 where both are <= 0."""
    a = np.sqrt(np.maximum(overlap, 0.0))
    b = np.sqrt(np.maximum(start_overlap, 0.0))
    total = a + b
    return np.where(total > 0.0, (2.0 / 3.0) * ks * ((a * a + a * b + b * b) / np.where(total > 0.0, total, 1.0)), 0.0)


def mindlin_move_stiffness_slope(start_overlap, overlap, ks):
    """d ``mindlin_move_stiffness`` / d overlap [N/m^2] = (1/3) ks (a + 2 b) / (a + b)^2, a = sqrt(overlap),
    b = sqrt(start_overlap) (0 where both are <= 0)."""
    a = np.sqrt(np.maximum(overlap, 0.0))
    b = np.sqrt(np.maximum(start_overlap, 0.0))
    total = a + b
    return np.where((total > 0.0) & (overlap > 0.0),
                    (1.0 / 3.0) * ks * ((a + 2.0 * b) / np.where(total > 0.0, total * total, 1.0)), 0.0)


def reduced_radius_root(radius_i, radius_j):
    """sqrt(R*) [m^0.5] of pairs of radii r_i, r_j [m] (arrays broadcast), R* = r_i r_j / (r_i + r_j)."""
    return np.sqrt(radius_i * radius_j / (radius_i + radius_j))


def hertz_pair_constants(law, radius_i, radius_j):
    """(kh, ks) [N/m^1.5] of pairs of radii r_i, r_j [m] (arrays broadcast): (4/3) E* sqrt(R*) and
    8 G* sqrt(R*), R* = r_i r_j / (r_i + r_j); ``law`` a ``HertzMindlinLaw``."""
    root = reduced_radius_root(radius_i, radius_j)
    return law.normal_modulus * root, law.shear_stiffness_modulus * root


class PairLaw:
    """A contact law evaluated for a batch of pairs (numpy, elementwise over overlaps).

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

    @property
    def linear(self) -> bool:
        """True for the linear law."""
        return self.name == "linear"

    def normal(self, overlap):
        """Normal force [N] at ``overlap`` [m], never tension."""
        return normal_force(overlap, self.kn) if self.linear else hertz_normal_force(overlap, self.kn)

    def normal_stiffness(self, overlap):
        """d f_n / d overlap [N/m] for overlap > 0 (the linear law: kn)."""
        return self.kn if self.linear else hertz_normal_stiffness(overlap, self.kn)

    def shear_stiffness(self, overlap):
        """Tangential stiffness kt [N/m] at ``overlap`` (the linear law: kt)."""
        return self.kt if self.linear else mindlin_shear_stiffness(overlap, self.kt)

    def move_stiffness(self, start_overlap, overlap):
        """Stiffness [N/m] by which a move from ``start_overlap`` to ``overlap`` grows the spring
        (the linear law: kt; Hertz-Mindlin: ``mindlin_move_stiffness``)."""
        return self.kt if self.linear else mindlin_move_stiffness(start_overlap, overlap, self.kt)

    def move_stiffness_slope(self, start_overlap, overlap):
        """d ``move_stiffness`` / d overlap [N/m^2] (the linear law: 0)."""
        return 0.0 if self.linear else mindlin_move_stiffness_slope(start_overlap, overlap, self.kt)


def pair_law(law, radius_i=None, radius_j=None) -> PairLaw:
    """``PairLaw`` of a contact-law declaration (``warp_hcell.core.parameters``) for pairs of radii
    r_i, r_j [m] (arrays broadcast; the linear law ignores them)."""
    if law.name == "linear":
        return PairLaw("linear", law.kn, law.kt)
    if radius_i is None or radius_j is None:
        raise ValueError(f"the {law.name} contact law needs the radii of the pairs")
    return PairLaw(law.name, *hertz_pair_constants(law, np.asarray(radius_i), np.asarray(radius_j)))
