"""The shared geometry of the compiled meso-ANN increment (numba); its records: ``training.fast_tables``.

Every array is cells LAST (one cell a vector lane, nothing reduced across cells), so that a
cell's result is bit-identical whatever batch it is in and whatever the CPU's vector width.
State layouts: size (2, n) [m], free (n_free, n) [m], shear (n_pairs, n) [N]; the probe
d_eps (n, 2) [-]. Sign convention: compression and contraction positive; local frame index
0 = n, 1 = t.
"""

import importlib.machinery
import importlib.util
import math
import os
import sys

import numba
import numpy as np

# The records are also this module's names: numba's cache indexes written before they moved to training.fast_tables
# name them here, and unpickling such an index must succeed for numba to find it stale and compile again.
from training.fast_tables import Advanced, Before, CellTables, Normalisation, Physics  # noqa: F401
from warp_hcell.core.contact import coulomb_cap as _coulomb_cap
from warp_hcell.core.contact import normal_force as _normal_force


def _load_numba_arraymath() -> None:
    """Import ``numba.np.arraymath`` (loaded by numba's set-up before the first compiled call) without
    ``scipy.linalg``: its import checks that BLAS is there by importing ``scipy.linalg.cython_blas``,
    which loads the whole ``scipy.linalg`` package (~0.2 s of CPU; these kernels call no BLAS). That
    extension module is loaded alone for the check and then taken out of ``sys.modules``, so that
    ``scipy.linalg``, and numba's BLAS calls, load it with its package as usual when needed. Nothing
    happens where either module is loaded already or scipy is not installed."""
    name = "scipy.linalg.cython_blas"
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules or name in sys.modules:
        return
    scipy = importlib.util.find_spec("scipy")
    if scipy is None or scipy.origin is None:
        return
    folder = os.path.join(os.path.dirname(scipy.origin), "linalg")
    path = next((p for p in (os.path.join(folder, "cython_blas" + s) for s in importlib.machinery.EXTENSION_SUFFIXES)
                 if os.path.exists(p)), None)
    if path is None:
        return
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        import numba.np.arraymath  # noqa: F401, PLC0415
    finally:
        sys.modules.pop(name, None)


_load_numba_arraymath()

normal_force = numba.njit(cache=True, error_model="numpy")(_normal_force)
"""``warp_hcell.core.contact.normal_force`` compiled for the kernels (scalars)."""
coulomb_cap = numba.njit(cache=True, error_model="numpy")(_coulomb_cap)
"""``warp_hcell.core.contact.coulomb_cap`` compiled for the kernels (scalars)."""


@numba.njit(cache=True, error_model="numpy", inline="always")
def carried_spring3(s0, s1, s2, u0, u1, u2):
    """The spatial spring (s0, s1, s2) [N] carried into the plane normal to the unit vector (u0, u1, u2), its
    length kept (``warp_hcell.dem.contact.carried_spring``): its tangential part, rescaled to the spring's length
    where that part is not zero. Returns the three components [N]."""
    along = s0 * u0 + s1 * u1 + s2 * u2
    q0, q1, q2 = s0 - along * u0, s1 - along * u1, s2 - along * u2
    before2 = s0 * s0 + s1 * s1 + s2 * s2
    after2 = q0 * q0 + q1 * q1 + q2 * q2
    if after2 > 0.0:
        ratio = math.sqrt(before2 / after2)
        q0, q1, q2 = q0 * ratio, q1 * ratio, q2 * ratio
    return q0, q1, q2


@numba.njit(cache=True, error_model="numpy")
def grain_positions(size, free, frac, free_dofs, x):
    """Grain centres into ``x`` (n_grains, dim, n) [m]: driven from ``size`` (dim, n), free from ``free``
    (n_free, n); dim = 2 or 3 (``frac.shape[1]``)."""
    n = size.shape[1]
    for g in range(frac.shape[0]):
        for a in range(frac.shape[1]):
            row, scale, size_a = x[g, a], frac[g, a], size[a]
            for c in range(n):
                row[c] = scale * size_a[c]
    for k in range(free_dofs.shape[0]):
        row, free_k = x[free_dofs[k, 0], free_dofs[k, 1]], free[k]
        for c in range(n):
            row[c] = free_k[c]


@numba.njit(cache=True, error_model="numpy")
def any_within(b0, b1, reach):
    """Whether some cell's pair may be within ``reach`` [m] of branch (b0, b1) (n,) each: a test without
    square roots whose margin (1e-9 of reach) covers their rounding, so that False means out of
    contact in every cell exactly as ``sqrt(b0^2 + b1^2) <= reach`` would decide."""
    bound = (reach * (1.0 + 1e-9)) ** 2
    near = False
    for c in range(b0.shape[0]):
        near |= b0[c] * b0[c] + b1[c] * b1[c] <= bound
    return near


@numba.njit(cache=True, error_model="numpy")
def pair_branch(x, pairs, radius, tol, p, b0, b1):
    """Pair p = (i, j) at the grain centres x (n_grains, 2, n) [m]: writes its branch x_j - x_i
    into b0, b1 (n,) [m] and returns (i, j, r_i + r_j [m], reach (r_i + r_j)(1 + tol) [m],
    whether some cell may be within reach (the test of ``any_within``))."""
    i = pairs[p, 0]
    j = pairs[p, 1]
    rsum = radius[i] + radius[j]
    reach = rsum * (1.0 + tol)
    xi0, xi1, xj0, xj1 = x[i, 0], x[i, 1], x[j, 0], x[j, 1]
    bound = (reach * (1.0 + 1e-9)) ** 2  # any_within's test, in the same pass
    near = 0
    for c in range(b0.shape[0]):
        branch0 = xj0[c] - xi0[c]
        branch1 = xj1[c] - xi1[c]
        b0[c] = branch0
        b1[c] = branch1
        near += np.int64(branch0 * branch0 + branch1 * branch1 <= bound)
    return i, j, rsum, reach, near > 0
