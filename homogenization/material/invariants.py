"""Stress invariants and the second-order work (spec section 9), in 2D and 3D.

2D: p = (sigma11 + sigma22) / 2 (mean stress), q = sigma11 - sigma22 (deviator; q > 0 when the
11 direction is the more compressed one), W2 = d_sigma : d_eps (second-order work per increment).

3D (``*_3d``): p = tr(sigma) / 3, q = sqrt(3 J2) with J2 = s : s / 2 the second invariant of the
deviatoric stress s = sigma - p I (q = abs(sigma1 - sigma3) on an axisymmetric triaxial path),
eps_v = tr(eps), and the Lode ratio b = (sigma2 - sigma3) / (sigma1 - sigma3).

Sign convention: compression and contraction positive. Stresses in N/m (2D) or Pa (3D),
strains [-]. All functions accept scalars or arrays of equal shape and work elementwise.
"""

from __future__ import annotations

import numpy as np


def mean_stress(sigma11, sigma22):
    """p = (sigma11 + sigma22) / 2 [N/m], compression positive."""
    return 0.5 * (np.asarray(sigma11) + np.asarray(sigma22))


def deviator(sigma11, sigma22):
    """q = sigma11 - sigma22 [N/m], positive when sigma11 is the larger compression."""
    return np.asarray(sigma11) - np.asarray(sigma22)


def volumetric_strain(eps11, eps22):
    """eps_v = eps11 + eps22 [-] (small strain), contraction positive."""
    return np.asarray(eps11) + np.asarray(eps22)


def second_order_work(sigma11, sigma22, sigma12, eps11, eps22, eps12=0.0) -> np.ndarray:
    """Second-order work W2 = d_sigma : d_eps per increment of a history [N/m].

    Args:
        sigma11, sigma22, sigma12: stress history [N/m], shape (n,), compression positive.
        eps11, eps22: strain history [-], shape (n,), contraction positive.
        eps12: tensor shear strain history [-], shape (n,) or scalar.

    Returns:
        W2 between consecutive states [N/m], shape (n - 1,):
        d_s11 d_e11 + d_s22 d_e22 + 2 d_s12 d_e12. In a constant-volume test this is
        dq * d_eps11, which changes sign at the q peak.
    """
    d = np.diff
    e12 = np.broadcast_to(np.asarray(eps12, dtype=np.float64), np.shape(eps11))
    return d(sigma11) * d(eps11) + d(sigma22) * d(eps22) + 2.0 * d(sigma12) * d(e12)


def mean_stress_3d(sigma11, sigma22, sigma33):
    """p = (sigma11 + sigma22 + sigma33) / 3 [Pa], compression positive."""
    return (np.asarray(sigma11) + np.asarray(sigma22) + np.asarray(sigma33)) / 3.0


def deviator_3d(sigma11, sigma22, sigma33, sigma23=0.0, sigma13=0.0, sigma12=0.0):
    """q = sqrt(3 J2) [Pa], J2 = ((s11 - s22)^2 + (s22 - s33)^2 + (s33 - s11)^2) / 6 + s23^2 + s13^2 + s12^2."""
    s11, s22, s33 = (np.asarray(v, dtype=np.float64) for v in (sigma11, sigma22, sigma33))
    shear = np.asarray(sigma23) ** 2 + np.asarray(sigma13) ** 2 + np.asarray(sigma12) ** 2
    J2 = ((s11 - s22) ** 2 + (s22 - s33) ** 2 + (s33 - s11) ** 2) / 6.0 + shear
    return np.sqrt(3.0 * J2)


def volumetric_strain_3d(eps11, eps22, eps33):
    """eps_v = eps11 + eps22 + eps33 [-] (small strain), contraction positive."""
    return np.asarray(eps11) + np.asarray(eps22) + np.asarray(eps33)


def lode_ratio(sigma1, sigma2, sigma3):
    """b = (sigma2 - sigma3) / (sigma1 - sigma3) [-] of principal stresses sigma1 >= sigma2 >= sigma3 (NaN where sigma1 = sigma3)."""
    s1, s2, s3 = (np.asarray(v, dtype=np.float64) for v in (sigma1, sigma2, sigma3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(s1 != s3, (s2 - s3) / np.where(s1 != s3, s1 - s3, 1.0), np.nan)
