"""2D stress invariants and the second-order work (spec section 9).

p = (sigma11 + sigma22) / 2 (mean stress), q = sigma11 - sigma22 (deviator; q > 0 when the
11 direction is the more compressed one), W2 = d_sigma : d_eps (second-order work per increment).

Sign convention: compression and contraction positive. Stresses in N/m (2D), strains [-].
All functions accept scalars or arrays of equal shape and work elementwise.
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
