"""The contact law of the package, written once for numpy and numba.

Linear normal spring without tension, incremental tangential spring with a Coulomb cap:

    f_n = kn max(overlap, 0),  f_s = clip(f_s,old + kt du, -mu f_n, +mu f_n),

with overlap = r_i + r_j - norm(x_j - x_i) [m] (negative: a gap) and du the tangential relative
displacement of the step [m]. The trial force f_s,old + kt du decides the sliding direction.

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
