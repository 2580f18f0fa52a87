"""Cell orientations, fabric weights, strain localisation and stress averaging.

Exports the ``Orientations`` set (theta_k = k pi / N with weights w_k, spec section 8),
``localise`` (macro strain increment -> per-cell (d_eps_n, d_eps_t), spec section 3) and
``average_moment`` (per-cell Love-Weber moments rotated to the macro frame and summed with
the weights, spec sections 7-8). The macro stress is sigma = average_moment / V with the
volume rule V = V0 * J (``VOLUME_RULE``, ``initial_volume``, ``volume_ratio_factor``).

Sign convention: compression and contraction positive. Macro tensors are given as their
three components (11, 22, 12) (tensor, not engineering, shear strain). Local frames:
index 0 = n = (cos theta, sin theta) (cell axis), index 1 = t = (-sin theta, cos theta).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VOLUME_RULE = (
    "V = V0*J, V0 = sum_k w_k V_cell,k in the initial state, J = prod over increments of "
    "(1 - d_eps11)(1 - d_eps22); V_cell = hexagon through the centres of the six grains "
    "(polygon through the centres of the driven outer grains for a general mesostructure)"
)
"""The volume rule, stated in every output file."""


@dataclass(frozen=True, eq=False)
class OrientationSet:
    """N oriented cells with their weights and the matrices that localise and average, in
    either dimension (``Orientations`` in the plane, ``orientation3d.Orientations3D``).

    Attributes:
        weights: w_k [-], shape (N,), summing to 1.
        localisation: L [-], shape (dim N, n_c) with n_c = 3 (2D) or 6 (3D) macro components:
            ``(L @ d_eps).reshape(N, dim)`` are the normal strains along each cell's axes.
        averaging: A [-], shape (n_c, dim^2 N): ``A @ moment.reshape(-1)`` is the weighted macro
            moment of per-cell moments ``moment`` (N, dim, dim) in the cell frames.
    """

    weights: np.ndarray
    localisation: np.ndarray
    averaging: np.ndarray

    @property
    def n_cells(self) -> int:
        """Number of oriented cells N."""
        return int(self.weights.shape[0])


@dataclass(frozen=True, eq=False)
class Orientations(OrientationSet):
    """A set of N cell orientations in the plane with fabric weights (``OrientationSet``).

    Build it with ``orientations``. Arrays are read-only.

    Attributes:
        theta: cell-axis angles theta_k = k pi / N [rad], shape (N,).
        weights: fabric weights w_k [-], shape (N,), summing to 1.
        localisation: matrix L [-], shape (2 N, 3), such that
            ``(L @ d_eps).reshape(N, 2)`` is (d_eps_n, d_eps_t) per cell for a macro
            increment d_eps = (d_eps11, d_eps22, d_eps12).
        averaging: matrix A [-], shape (3, 4 N), such that
            ``A @ moment.reshape(-1)`` is the weighted macro moment (S11, S22, S12) of the
            per-cell local moments ``moment`` of shape (N, 2, 2).
    """

    theta: np.ndarray

    @property
    def axes(self) -> np.ndarray:
        """Each cell's axis n = (cos theta, sin theta) in the macro frame [-], shape (N, 2)."""
        return np.stack([np.cos(self.theta), np.sin(self.theta)], axis=1)

    @property
    def axis_angle_deg(self) -> np.ndarray:
        """theta_k in degrees [deg], shape (N,)."""
        return np.degrees(self.theta)


def fabric_weights(theta: np.ndarray, anisotropy: float = 0.0, direction_deg: float = 0.0) -> np.ndarray:
    """Weights w_k = w(theta_k) pi / N with w(theta) = (1 + a_f cos 2(theta - b_f)) / pi.

    Args:
        theta: equally spaced orientations k pi / N [rad], shape (N,).
        anisotropy: fabric anisotropy a_f [-], in [0, 1); 0 gives w_k = 1 / N.
        direction_deg: preferred direction b_f of the fabric [deg].

    Returns:
        Weights [-], shape (N,), positive, summing to 1 (exactly so for N >= 2).
    """
    if not (0.0 <= anisotropy < 1.0):
        raise ValueError(f"fabric anisotropy = {anisotropy:g} is outside [0, 1)")
    b = math.radians(direction_deg)
    return (1.0 + anisotropy * np.cos(2.0 * (theta - b))) / theta.shape[0]


def orientations(n_orientations: int, *, anisotropy: float = 0.0, direction_deg: float = 0.0) -> Orientations:
    """Orientation set theta_k = k pi / N, k = 0..N-1, with fabric weights (spec section 8).

    Args:
        n_orientations: N >= 1.
        anisotropy: fabric anisotropy a_f [-], in [0, 1) (0 = isotropic fabric).
        direction_deg: preferred fabric direction b_f [deg].
    """
    n = int(n_orientations)
    if n < 1:
        raise ValueError(f"n_orientations = {n_orientations} must be >= 1")
    theta = np.arange(n, dtype=np.float64) * (math.pi / n)
    w = fabric_weights(theta, anisotropy, direction_deg)
    c, s = np.cos(theta), np.sin(theta)
    cc, ss, sc = c * c, s * s, s * c

    # d_eps_n = n.d_eps.n, d_eps_t = t.d_eps.t with n = (c, s), t = (-s, c).
    loc = np.empty((n, 2, 3))
    loc[:, 0] = np.stack([cc, ss, 2.0 * sc], axis=1)
    loc[:, 1] = np.stack([ss, cc, -2.0 * sc], axis=1)

    # Macro S = sum_k w_k R_k S_k R_k^T (R columns n, t), symmetrised shear component.
    avg = np.empty((3, n, 2, 2))
    avg[0] = np.stack([cc, -sc, -sc, ss], axis=1).reshape(n, 2, 2)
    avg[1] = np.stack([ss, sc, sc, cc], axis=1).reshape(n, 2, 2)
    avg[2] = np.stack([sc, 0.5 * (cc - ss), 0.5 * (cc - ss), -sc], axis=1).reshape(n, 2, 2)
    avg *= w[None, :, None, None]

    arrays = {"theta": theta, "weights": w, "localisation": loc.reshape(2 * n, 3), "averaging": avg.reshape(3, 4 * n)}
    for a in arrays.values():
        a.flags.writeable = False
    return Orientations(**arrays)


def localise(orient: OrientationSet, d_eps: np.ndarray) -> np.ndarray:
    """Per-cell local strain increments of a macro strain increment (spec section 3).

    Args:
        orient: the orientation set (either dimension).
        d_eps: macro increment [-], compression positive, tensor shear components:
            (d_eps11, d_eps22, d_eps12), shape (3,), in 2D; the six ``orientation3d.COMPONENTS``
            in 3D.

    Returns:
        The normal strains along each cell's axes [-], shape (N, dim) ((d_eps_n, d_eps_t) in
        2D), compression positive; the shears are dropped (model hypothesis).
    """
    return (orient.localisation @ np.asarray(d_eps, dtype=np.float64)).reshape(orient.n_cells, -1)


def average_moment(orient: OrientationSet, moment: np.ndarray) -> np.ndarray:
    """Weighted sum of per-cell moments rotated to the macro frame (spec sections 7-8).

    Args:
        orient: the orientation set (either dimension).
        moment: Love-Weber moments S in each cell's frame [N m], shape (N, dim, dim),
            compression positive.

    Returns:
        The macro moment [N m], shape (3,) (S11, S22, S12) in 2D, (6,) in 3D, compression
        positive; divide by the macro volume V [m^2 or m^3] to get sigma.
    """
    return orient.averaging @ np.ascontiguousarray(moment, dtype=np.float64).reshape(-1)


def initial_volume(orient: OrientationSet, volume: np.ndarray) -> float:
    """V0 = sum_k w_k V_cell,k [m^2 or m^3] from the initial cell areas or volumes, shape (N,)."""
    return float(orient.weights @ np.asarray(volume, dtype=np.float64))


def volume_ratio_factor(d_eps: np.ndarray) -> float:
    """Factor prod_a (1 - d_eps_aa) [-] by which one increment multiplies J = V / V0: over
    (11, 22) for the three components of a 2D increment, (11, 22, 33) for the six of a 3D one."""
    dim = 2 if len(d_eps) == 3 else 3
    return math.prod(1.0 - float(d_eps[a]) for a in range(dim))
