"""Cell orientations and their weights, strain localisation and stress averaging, in 2D and 3D.

An orientation set holds N cell frames R_k [-] (N, d, d), whose columns are the cell's local axes
in the macro frame ((n, t) or (n, t1, t2), ``warp_hcell.core.dimension``), their weights w_k
(summing to 1) and the two matrices built from them the same way in both dimensions:

- Localisation (spec section 3; model hypothesis: cells take the normal strains of their axes,
  shear dropped): d_eps_a = R_k e_a . d_eps . R_k e_a for each local axis a (``localise``).
- Averaging (spec sections 7-8): S = sum_k w_k R_k S_k R_k^T with S_k the cell's Love-Weber
  moment in its frame [N m] (``average_moment``); sigma = S / V with the volume rule V = V0 J,
  V0 = sum_k w_k V_cell,k, J = prod over increments of prod_a (1 - d_eps_aa) (``VOLUME_RULE``,
  ``VOLUME_RULE_3D``, ``initial_volume``, ``volume_ratio_factor``).

The quadrature is the dimension's: in the plane theta_k = k pi / N with fabric weights
(``orientations``, spec section 8); in space a Lebedev rule of cell axes on the hemisphere
(``hemisphere_rule``: one point of each antipodal pair, twice its weight) times ``n_spins`` spins
psi_kj = (j + phi_k) * spin_period / n_spins of the lateral axes about each axis
(``orientations_3d``). The phase phi_k = frac(k g), g = (sqrt(5) - 1) / 2 (``SPIN_STAGGER``)
staggers the spins from axis to axis, so that the axes together sample the spin at distinct
phases (a cell's response is not smooth in its spin); each axis's spins stay equally spaced, so
the rule stays exact for the spin's harmonics below n_spins, but gives up the cube symmetry of
aligned spins (``staggered=False``; docs/triaxial.md, Quadrature). t1 at psi = 0 is the unit
vector of e x n with e the macro axis least aligned with n (ties to the lower index).

Kinematics of a 3D cell (``KINEMATICS``): ``"projected"`` drives each axis by the normal strain
above; ``"axisymmetric"`` (``hcell3d-axisym``, docs/model.md section 14) drives the cell by its
axisymmetric part lat = (d_eps_t1 + d_eps_t2) / 2 only: d_eps_n' = d_eps_n - c, d_eps_t1' =
d_eps_t2' = lat - c with c = (d_eps_n - lat) / 6 (``AXISYMMETRIC_MAP``), so that each plane (n, t1),
(n, t2) keeps the cell's axisymmetric deviator and takes two thirds of its volumetric strain;
``"amplified"`` (``hcell3d-sand``, docs/triaxial.md) is the same with that deviator multiplied by the gain
g = 2 (``axisymmetric_map``; ``hcell.KINEMATICS_GAIN``).

Macro tensors are given by their Voigt components (``Dimension.components``: (11, 22, 12) or
(11, 22, 33, 23, 13, 12); tensor, not engineering, shear strains). Sign convention: compression
and contraction positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from warp_hcell.core.dimension import Dimension, dimension
from warp_hcell.mesostructures.hcell import AXISYMMETRIC_KINEMATICS, KINEMATICS_GAIN
from warp_hcell.mesostructures.mesostructure import Mesostructure

VOLUME_RULE = (
    "V = V0*J, V0 = sum_k w_k V_cell,k in the initial state, J = prod over increments of "
    "(1 - d_eps11)(1 - d_eps22); V_cell = hexagon through the centres of the six grains "
    "(polygon through the centres of the driven outer grains for a general mesostructure)"
)
"""The planar volume rule, stated in every output file."""
VOLUME_RULE_3D = (
    "V = V0*J, V0 = sum_k w_k V_cell,k in the initial state, J = prod over increments of "
    "(1 - d_eps11)(1 - d_eps22)(1 - d_eps33); V_cell = volume of the polyhedron through the centres "
    "of the cell's outer grains (its declared triangulated faces)"
)
"""The spatial volume rule, stated in every output file."""
SPIN_STAGGER = (5.0**0.5 - 1.0) / 2.0
"""Phase step phi_{k+1} - phi_k of the spins from one axis to the next, as a fraction of one spin
step (module docstring) [-]."""
LEBEDEV_ORDERS = (3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31, 35, 41, 47, 53, 59, 65, 71, 77, 83, 89, 95,
                  101, 107, 113, 119, 125, 131)
"""Lebedev orders accepted (``scipy.integrate.lebedev_rule``), degree of exactness on the sphere."""
KINEMATICS = ("projected", *KINEMATICS_GAIN)
"""Ways a macro increment drives the axes of a 3D cell (module docstring)."""
AXISYMMETRIC_MAP = np.array([[5.0, 0.5, 0.5], [-1.0, 3.5, 3.5], [-1.0, 3.5, 3.5]]) / 6.0
"""(d_eps_n', d_eps_t1', d_eps_t2') = AXISYMMETRIC_MAP @ (d_eps_n, d_eps_t1, d_eps_t2) [-] of the axisymmetric
kinematics (module docstring)."""


def axisymmetric_map(gain: float) -> np.ndarray:
    """The 3 x 3 map of the cell-axis strains (d_eps_n, d_eps_t1, d_eps_t2) [-] that drives a cell by its
    axisymmetric part with the deviator multiplied by ``gain`` [-]: d_eps_n' = v/3 + g dev/2, d_eps_t1' =
    d_eps_t2' = v/3 - g dev/2 with v = d_eps_n + d_eps_t1 + d_eps_t2 and dev = d_eps_n - (d_eps_t1 + d_eps_t2)/2.
    ``gain`` 1 is ``AXISYMMETRIC_MAP`` (to rounding)."""
    deviator = np.array([[0.5, -0.25, -0.25], [-0.5, 0.25, 0.25], [-0.5, 0.25, 0.25]])
    return np.full((3, 3), 1.0 / 3.0) + float(gain) * deviator


@dataclass(frozen=True, eq=False)
class OrientationSet:
    """N oriented cells with their weights and the matrices that localise and average, in either
    dimension d (``Orientations`` in the plane, ``Orientations3D`` in space). Arrays are read-only.

    Attributes:
        frames: rotations R_k [-], shape (N, d, d), columns the cell's local axes in the macro frame.
        weights: w_k [-], shape (N,), summing to 1.
        localisation: L [-], shape (d N, n_voigt): ``(L @ d_eps).reshape(N, d)`` are the normal
            strains along each cell's axes for a macro increment d_eps (Voigt components).
        averaging: A [-], shape (n_voigt, d^2 N): ``A @ moment.reshape(-1)`` is the weighted macro
            moment (Voigt components) of per-cell moments ``moment`` (N, d, d) in the cell frames.
    """

    frames: np.ndarray
    weights: np.ndarray
    localisation: np.ndarray
    averaging: np.ndarray

    @property
    def n_cells(self) -> int:
        """Number of oriented cells N."""
        return int(self.weights.shape[0])

    @property
    def axes(self) -> np.ndarray:
        """Each cell's axis n in the macro frame [-], shape (N, d)."""
        return self.frames[:, :, 0]


@dataclass(frozen=True, eq=False)
class Orientations(OrientationSet):
    """A set of N cell orientations in the plane with fabric weights (``OrientationSet``, d = 2;
    frames (n, t) with n = (cos theta, sin theta), t = (-sin theta, cos theta)).

    Build it with ``orientations``.

    Attributes:
        theta: cell-axis angles theta_k = k pi / N [rad], shape (N,).
    """

    theta: np.ndarray

    @property
    def axis_angle_deg(self) -> np.ndarray:
        """theta_k in degrees [deg], shape (N,)."""
        return np.degrees(self.theta)

    @property
    def recorded_frames(self) -> None:
        """The frames a run records beside ``axis_angle_deg``: none (theta gives them)."""
        return None


@dataclass(frozen=True, eq=False)
class Orientations3D(OrientationSet):
    """A set of N oriented cells in space (``OrientationSet``, d = 3; frames (n, t1, t2)).

    Build it with ``orientations_3d``.

    Attributes:
        order: Lebedev order of the axes; n_spins: spins per axis; spin_period_deg: psi period [deg];
            staggered: whether the spins are staggered from axis to axis (``SPIN_STAGGER``);
            kinematics: how an increment drives the cell axes (``KINEMATICS``).
    """

    order: int
    n_spins: int
    spin_period_deg: float
    staggered: bool = True
    kinematics: str = "projected"

    @property
    def axis_angle_deg(self) -> np.ndarray:
        """Angle between each cell axis and macro axis 1, in [0, 90] [deg], shape (N,)."""
        return np.degrees(np.arccos(np.clip(np.abs(self.frames[:, 0, 0]), 0.0, 1.0)))

    @property
    def recorded_frames(self) -> np.ndarray:
        """The frames a run records beside ``axis_angle_deg`` (which loses the spin): a copy of ``frames``."""
        return np.array(self.frames)


def _matrices(frames: np.ndarray, weights: np.ndarray, space: Dimension) -> dict[str, np.ndarray]:
    """The read-only arrays of an ``OrientationSet`` of ``frames`` (N, d, d) and ``weights`` (N,):
    the localisation and the averaging matrices of the module docstring."""
    count, d = frames.shape[0], space.dim
    loc = np.empty((count, d, space.n_voigt))
    avg = np.empty((space.n_voigt, count, d, d))
    for m, (i, j) in enumerate(space.index):
        factor = 1.0 if i == j else 2.0
        loc[:, :, m] = factor * frames[:, i, :] * frames[:, j, :]
        avg[m] = 0.5 * (frames[:, i, :, None] * frames[:, j, None, :] + frames[:, j, :, None] * frames[:, i, None, :])
    avg *= weights[None, :, None, None]
    return {"frames": frames, "weights": weights, "localisation": loc.reshape(d * count, space.n_voigt),
            "averaging": avg.reshape(space.n_voigt, d * d * count)}


def _read_only(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    for a in arrays.values():
        a.flags.writeable = False
    return arrays


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
    c, s = np.cos(theta), np.sin(theta)
    frames = np.stack([np.stack([c, -s], axis=1), np.stack([s, c], axis=1)], axis=1)
    arrays = _matrices(frames, fabric_weights(theta, anisotropy, direction_deg), dimension(2))
    return Orientations(**_read_only({**arrays, "theta": theta}))


def kinematics_of(parameters: Mapping[str, float]) -> str:
    """The kinematics (``KINEMATICS``) that a 3D cell's ``parameters`` declare (a mesostructure's, or the
    ``cell_parameters`` a certificate recorded): "amplified" where ``hcell.AXISYMMETRIC_KINEMATICS`` is its
    gain (``hcell3d-sand``), "axisymmetric" where it is another nonzero value (``hcell3d-axisym``), else
    "projected"."""
    gain = parameters.get(AXISYMMETRIC_KINEMATICS, 0.0)
    if not gain:
        return "projected"
    return "amplified" if gain == KINEMATICS_GAIN["amplified"] else "axisymmetric"


def cell_kinematics(mesostructure: Mesostructure) -> str:
    """The kinematics (``KINEMATICS``) a 3D mesostructure declares (``kinematics_of`` its parameters)."""
    return kinematics_of(mesostructure.parameters)


def hemisphere_rule(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Cell axes and weights: a Lebedev rule with one point of each antipodal pair, weights summing to 1.

    Args:
        order: Lebedev order (``LEBEDEV_ORDERS``).

    Returns:
        axes (M, 3) unit vectors, weights (M,) [-].
    """
    from scipy.integrate import lebedev_rule  # noqa: PLC0415 (scipy: only where a 3D rule is built)

    if order not in LEBEDEV_ORDERS:
        raise ValueError(f"Lebedev order {order} is not one of {', '.join(map(str, LEBEDEV_ORDERS))}")
    points, weights = lebedev_rule(order)
    points = points.T
    keep = np.zeros(points.shape[0], dtype=bool)
    for k, x in enumerate(points):
        first = next(v for v in x if abs(v) > 1e-12)  # the sign of the first nonzero coordinate picks one of +-x
        keep[k] = first > 0.0
    axes, w = points[keep], weights[keep]
    if not np.allclose(np.sort(np.concatenate([axes, -axes]), axis=0), np.sort(points, axis=0), atol=1e-12):
        raise ValueError(f"Lebedev order {order}: the points are not antipodal pairs")
    return axes, w / w.sum()


def reference_lateral(axis: np.ndarray) -> np.ndarray:
    """t1 at psi = 0 for each axis (M, 3): unit e x n, e the macro axis least aligned with n."""
    e = np.eye(3)[np.argmin(np.abs(axis), axis=1)]
    t1 = np.cross(e, axis)
    return t1 / np.linalg.norm(t1, axis=1, keepdims=True)


def orientations_3d(order: int = 11, n_spins: int = 4, *, spin_period_deg: float = 90.0,
                    staggered: bool = True, kinematics: str = "projected") -> Orientations3D:
    """The orientation set of ``order`` x ``n_spins`` (module docstring).

    Args:
        order: Lebedev order of the axes (11: 25 axes on the hemisphere).
        n_spins: spins per axis, >= 1.
        spin_period_deg: period of the cell's spin symmetry [deg], in (0, 360].
        staggered: stagger the spins from axis to axis (``SPIN_STAGGER``); False: every axis has
            the spins psi_j = j * spin_period / n_spins.
        kinematics: "projected", "axisymmetric" or "amplified" (``KINEMATICS``, module docstring).
    """
    n_spins = int(n_spins)
    if n_spins < 1:
        raise ValueError(f"n_spins = {n_spins} must be >= 1")
    if not 0.0 < spin_period_deg <= 360.0:
        raise ValueError(f"spin period {spin_period_deg:g} deg is outside (0, 360]")
    if kinematics not in KINEMATICS:
        raise ValueError(f"kinematics {kinematics!r} is not one of {', '.join(KINEMATICS)}")
    axes, axis_weights = hemisphere_rule(order)
    t1_ref = reference_lateral(axes)
    t2_ref = np.cross(axes, t1_ref)
    phase = (np.arange(axes.shape[0]) * SPIN_STAGGER) % 1.0 if staggered else np.zeros(axes.shape[0])
    psi = np.radians(spin_period_deg) * (np.arange(n_spins)[None, :] + phase[:, None]) / n_spins
    c, s = np.cos(psi)[:, :, None], np.sin(psi)[:, :, None]
    n = np.repeat(axes[:, None, :], n_spins, axis=1)
    t1 = c * t1_ref[:, None, :] + s * t2_ref[:, None, :]
    t2 = -s * t1_ref[:, None, :] + c * t2_ref[:, None, :]
    frames = np.stack([n, t1, t2], axis=-1).reshape(-1, 3, 3)
    arrays = _matrices(frames, np.repeat(axis_weights / n_spins, n_spins), dimension(3))
    if kinematics != "projected":
        count = frames.shape[0]
        mapping = AXISYMMETRIC_MAP if kinematics == "axisymmetric" else axisymmetric_map(KINEMATICS_GAIN[kinematics])
        arrays["localisation"] = np.einsum("ab,kbm->kam", mapping,
                                           arrays["localisation"].reshape(count, 3, 6)).reshape(3 * count, 6)
    return Orientations3D(**_read_only(arrays), order=int(order), n_spins=n_spins,
                          spin_period_deg=float(spin_period_deg), staggered=bool(staggered), kinematics=kinematics)


def localise(orient: OrientationSet, d_eps: np.ndarray) -> np.ndarray:
    """Per-cell local strain increments of a macro strain increment (spec section 3).

    Args:
        orient: the orientation set (either dimension).
        d_eps: macro increment [-], Voigt components (``Dimension.components``), shape (n_voigt,),
            compression positive, tensor shear components.

    Returns:
        The normal strains along each cell's axes [-], shape (N, d) ((d_eps_n, d_eps_t) in 2D),
        compression positive; the shears are dropped (model hypothesis).
    """
    return (orient.localisation @ np.asarray(d_eps, dtype=np.float64)).reshape(orient.n_cells, -1)


def average_moment(orient: OrientationSet, moment: np.ndarray) -> np.ndarray:
    """Weighted sum of per-cell moments rotated to the macro frame (spec sections 7-8).

    Args:
        orient: the orientation set (either dimension).
        moment: Love-Weber moments S in each cell's frame [N m], shape (N, d, d), compression positive.

    Returns:
        The macro moment [N m], Voigt components, shape (n_voigt,), compression positive; divide by
        the macro volume V [m^2 or m^3] to get sigma.
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
