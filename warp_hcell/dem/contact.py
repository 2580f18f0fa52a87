"""The contact law in Warp (float64): the pieces the 2D and the 3D cell-step kernels share.

The law of ``warp_hcell.core.contact`` (its numpy/numba form): f_n = kn max(overlap, 0), the
tangential spring grows by kt times the tangential relative displacement and is capped at
mu f_n along the trial force; regime 1 (sticking) or 2 (sliding: at the cap with f_n > 0) for a
pair within the contact tolerance. Comparisons stand for max/clamp (no NaN handling on the hot
path); the results equal the numpy form's bit for bit (``tests/test_contact_law_conformance.py``).

The other laws (``warp_hcell.dem.laws``) use the regimes and the carried spring below.

Units: overlaps and displacements [m], stiffnesses [N/m], forces [N], mu [-].
"""

from __future__ import annotations

import warp as wp

from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def normal_force(overlap: wp.float64, kn: wp.float64):
    """Normal (repulsive) force kn max(overlap, 0) [N]; overlap = r_i + r_j - distance [m]."""
    zero = wp.float64(0.0)
    return kn * wp.where(overlap > zero, overlap, zero)


@wp.func
def contact_regime(normal: wp.float64, tangential: wp.float64, cap: wp.float64):
    """2 (sliding) where a loaded contact's tangential force size ``tangential`` [N] reaches ``cap``
    = mu f_n [N], else 1 (sticking); a float64 to compare with the previous substep's."""
    return wp.where(normal > wp.float64(0.0) and tangential >= cap, wp.float64(2.0), wp.float64(1.0))


@wp.func
def contact_law(
    overlap: wp.float64,
    shear_increment: wp.float64,
    shear_force: wp.float64,
    kn: wp.float64,
    kt: wp.float64,
    mu: wp.float64,
):
    """The planar law: linear normal spring without tension, tangential spring with Coulomb cap.

    Args:
        overlap: r_i + r_j - norm(x_j - x_i) [m] (negative = gap within the contact tolerance).
        shear_increment: tangential relative displacement of the substep [m].
        shear_force: tangential force before the substep [N].
        kn, kt: normal and tangential stiffness [N/m]; mu: friction coefficient [-].

    Returns:
        (normal force >= 0 [N], new tangential force [N]); the trial force decides the
        sliding direction: f_s = clip(f_s + kt du, -mu f_n, +mu f_n).
    """
    normal = normal_force(overlap, kn)
    cap = mu * normal
    trial = shear_force + kt * shear_increment
    return normal, wp.where(trial > cap, cap, wp.where(trial < -cap, -cap, trial))


@wp.func
def carried_spring(shear_force: wp.vec3d, normal: wp.vec3d):
    """The tangential spring carried into the tangent plane of ``normal`` (unit): projected, then
    rescaled to its former magnitude, by sqrt(norm(before)^2 / norm(after)^2) (zero stays zero)."""
    zero = wp.float64(0.0)
    projected = shear_force - wp.dot(shear_force, normal) * normal
    before2 = wp.dot(shear_force, shear_force)
    after2 = wp.dot(projected, projected)
    return wp.where(after2 > zero, projected * wp.sqrt(before2 / wp.where(after2 > zero, after2, wp.float64(1.0))),
                    projected)


@wp.func
def contact_law_3d(
    overlap: wp.float64,
    shear_increment: wp.vec3d,
    carried: wp.vec3d,
    kn: wp.float64,
    kt: wp.float64,
    mu: wp.float64,
):
    """The law in space: as ``contact_law``, the cap along the trial force's own direction.

    Args:
        overlap: r_i + r_j - norm(x_j - x_i) [m].
        shear_increment: tangential relative displacement of the substep [m], in the tangent plane.
        carried: the spring before the substep, already in the tangent plane (``carried_spring``) [N].
        kn, kt [N/m]; mu [-].

    Returns:
        (normal force >= 0 [N], new tangential force vector [N], regime: 1 sticking, 2 sliding).
    """
    return capped_spring(normal_force(overlap, kn), carried + kt * shear_increment, mu)


@wp.func
def capped_spring(normal: wp.float64, trial: wp.vec3d, mu: wp.float64):
    """A spatial pair's (normal force f_n [N], the trial spring [N] capped at mu f_n along its own
    direction, regime: 1 sticking, 2 sliding), every law's cap."""
    zero = wp.float64(0.0)
    cap = mu * normal
    size = wp.length(trial)
    shear = wp.where(size > cap, trial * (cap / wp.where(size > zero, size, wp.float64(1.0))), trial)
    return normal, shear, contact_regime(normal, size, cap)
