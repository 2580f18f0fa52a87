"""The Hertz-Mindlin contact law in numpy (``warp_hcell.core.parameters.HertzMindlinLaw``).

The stiffnesses are functions of the overlap: f_n = kh delta sqrt(delta) and kt = ks sqrt(delta),
delta = max(overlap, 0), with the pair constants kh = (4/3) E* sqrt(R*) and ks = 8 G* sqrt(R*)
[N/m^1.5] (``pair_constants``); the Coulomb cap is the linear law's. A move from overlap delta0 to
delta1 grows the spring by the mean of kt over the move (delta linear in the move) times du:

    kt(delta0, delta1) = (2/3) ks (delta1 + sqrt(delta0 delta1) + delta0) / (sqrt(delta1) + sqrt(delta0))

(= ks sqrt(delta) where delta0 = delta1; exact for a contact that closes within the move), in
every runtime (``move_stiffness``). Interface: ``warp_hcell.core.laws``.
"""

from __future__ import annotations

import numpy as np

from warp_hcell.core.contact import reduced_radius_root


def pair_constants(law, radius_i=None, radius_j=None):
    """(kh, ks) [N/m^1.5] of pairs of radii r_i, r_j [m] (arrays broadcast): (4/3) E* sqrt(R*) and
    8 G* sqrt(R*), R* = r_i r_j / (r_i + r_j); ``law`` a ``HertzMindlinLaw``."""
    if radius_i is None or radius_j is None:
        raise ValueError(f"the {law.name} contact law needs the radii of the pairs")
    root = reduced_radius_root(np.asarray(radius_i), np.asarray(radius_j))
    return law.normal_modulus * root, law.shear_stiffness_modulus * root


def normal_force(overlap, kh):
    """Hertz normal force f_n = kh delta sqrt(delta) [N], delta = max(overlap, 0) [m]; kh [N/m^1.5]."""
    delta = np.maximum(overlap, 0.0)
    return kh * (delta * np.sqrt(delta))


def normal_stiffness(overlap, kh):
    """Tangent normal stiffness d f_n / d overlap = 1.5 kh sqrt(delta) [N/m] (0 without overlap)."""
    return 1.5 * kh * np.sqrt(np.maximum(overlap, 0.0))


def shear_stiffness(overlap, ks):
    """Mindlin tangential stiffness kt = ks sqrt(delta) [N/m], delta = max(overlap, 0); ks [N/m^1.5]."""
    return ks * np.sqrt(np.maximum(overlap, 0.0))


def move_stiffness(start_overlap, overlap, ks):
    """Mean Mindlin stiffness [N/m] of a move from ``start_overlap`` to ``overlap`` [m] (module
    docstring); 0 where both are <= 0."""
    a = np.sqrt(np.maximum(overlap, 0.0))
    b = np.sqrt(np.maximum(start_overlap, 0.0))
    total = a + b
    return np.where(total > 0.0, (2.0 / 3.0) * ks * ((a * a + a * b + b * b) / np.where(total > 0.0, total, 1.0)), 0.0)


def move_stiffness_slope(start_overlap, overlap, ks):
    """d ``move_stiffness`` / d overlap [N/m^2] = (1/3) ks (a + 2 b) / (a + b)^2, a = sqrt(overlap),
    b = sqrt(start_overlap) (0 where both are <= 0)."""
    a = np.sqrt(np.maximum(overlap, 0.0))
    b = np.sqrt(np.maximum(start_overlap, 0.0))
    total = a + b
    return np.where((total > 0.0) & (overlap > 0.0),
                    (1.0 / 3.0) * ks * ((a + 2.0 * b) / np.where(total > 0.0, total * total, 1.0)), 0.0)
