"""Cell orientations in 3D: a spherical quadrature of cell axes times spins about them.

A 3D cell is oriented by its axis n (a point of the unit hemisphere: n and -n are the same
cell) and a spin psi of its lateral axes (t1, t2) about n. The orientation set is a Lebedev rule
on the sphere (``scipy.integrate.lebedev_rule``; exact for spherical polynomials up to its
order), of which one point of each antipodal pair is kept with twice its weight, times
``n_spins`` equally spaced spins about each axis k, psi_kj = (j + phi_k) * spin_period / n_spins
(spin_period: the cell's, ``Mesostructure.spin_period_deg``). The phase phi_k = frac(k g), g =
(sqrt(5) - 1) / 2 (``SPIN_STAGGER``, a Kronecker sequence), staggers the spins from one axis to
the next, so that the axes together sample the spin at n_axes distinct phases instead of the
same n_spins: a cell's response is not smooth in its spin (contacts open and slide), and with
aligned spins doubling them moved triaxial curves by 1.4 % of p0 where staggered spins move them
by 0.11 % (docs/triaxial.md, Quadrature). Each axis's spins stay equally spaced over the period,
so the rule keeps the exactness of aligned spins for the harmonics of the spin below n_spins.
What staggering gives up is the cube symmetry of the set: with aligned spins an axisymmetric
load along a macro axis gives sigma22 = sigma33 and zero shear stresses to round-off; with
staggered spins they differ by the quadrature error (on an undrained test at 2e5 Pa to 15 %:
8e-5 of the largest p on 6160 cells, 3-4 % on 14 cells). ``staggered=False`` gives
the aligned rule.
Weights are the Lebedev weight over the number of spins (an isotropic fabric), summing to 1.

Frames: ``frames[k]`` is the rotation R_k [-] (3, 3) whose columns are (n, t1, t2) in the macro
frame; t1 at psi = 0 is the unit vector of e x n with e the macro axis least aligned with n
(ties to the lower index), t2 = n x t1.

Macro tensors are given by their six components in the order (11, 22, 33, 23, 13, 12) (tensor,
not engineering, shear strains). Sign convention: compression and contraction positive.

- Localisation (model hypothesis: cells take the normal strains of their axes, shear dropped):
  d_eps_n = n . d_eps . n, d_eps_t1 = t1 . d_eps . t1, d_eps_t2 = t2 . d_eps . t2.
- Averaging: S = sum_k w_k R_k S_k R_k^T with S_k the cell's Love-Weber moment in its frame
  [N m]; sigma = S / V, V = V0 J, V0 = sum_k w_k V_cell,k, J = prod over increments of
  (1 - d_eps11)(1 - d_eps22)(1 - d_eps33).

Kinematics (``KINEMATICS``): ``"projected"`` (the default) drives each cell axis by the normal
strain above. ``"axisymmetric"`` (the cell kind ``hcell3d-axisym``, docs/model.md section 14)
drives the cell by its axisymmetric part only, lat = (d_eps_t1 + d_eps_t2) / 2, mapped so that
each plane (n, t1), (n, t2) of the cell keeps the cell's axisymmetric deviator d_eps_n - lat and
takes two thirds of the cell's volumetric strain d_eps_n + 2 lat as its area strain (what a
homothetic strain gives a plane): d_eps_n' = d_eps_n - c, d_eps_t1' = d_eps_t2' = lat - c with
c = (d_eps_n - lat) / 6 (``AXISYMMETRIC_MAP``). An isotropic increment drives the cell exactly
as the projected kinematics do; on an isochoric path every plane of every cell is isochoric,
as every 2D cell is on a constant-volume path. The averaging is the Love-Weber sum above in both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from homogenization.material.orientation import (  # noqa: F401 (localise, average_moment and the volume rule of both dimensions)
    average_moment,
    initial_volume,
    localise,
    OrientationSet,
    volume_ratio_factor,
)
from warp_hcell.mesostructures.hcell import AXISYMMETRIC_KINEMATICS
from warp_hcell.mesostructures.mesostructure import Mesostructure

COMPONENTS = ("11", "22", "33", "23", "13", "12")
"""Order of the six components of a macro tensor."""
_INDEX = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))
"""(i, j) of each component."""
SPIN_STAGGER = (5.0**0.5 - 1.0) / 2.0
"""Phase step phi_{k+1} - phi_k of the spins from one axis to the next, as a fraction of one spin
step (module docstring) [-]."""
LEBEDEV_ORDERS = (3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31, 35, 41, 47, 53, 59, 65, 71, 77, 83, 89, 95,
                  101, 107, 113, 119, 125, 131)
"""Lebedev orders accepted (``scipy.integrate.lebedev_rule``), degree of exactness on the sphere."""
VOLUME_RULE = (
    "V = V0*J, V0 = sum_k w_k V_cell,k in the initial state, J = prod over increments of "
    "(1 - d_eps11)(1 - d_eps22)(1 - d_eps33); V_cell = volume of the polyhedron through the centres "
    "of the cell's outer grains (its declared triangulated faces)"
)
"""The 3D volume rule, stated in every output file."""
KINEMATICS = ("projected", "axisymmetric")
"""Ways a macro increment drives the axes of a 3D cell (module docstring)."""
AXISYMMETRIC_MAP = np.array([[5.0, 0.5, 0.5], [-1.0, 3.5, 3.5], [-1.0, 3.5, 3.5]]) / 6.0
"""(d_eps_n', d_eps_t1', d_eps_t2') = AXISYMMETRIC_MAP @ (d_eps_n, d_eps_t1, d_eps_t2) [-] of the axisymmetric
kinematics (module docstring)."""


def kinematics_of(parameters: Mapping[str, float]) -> str:
    """The kinematics (``KINEMATICS``) that a 3D cell's ``parameters`` declare (a mesostructure's, or the
    ``cell_parameters`` a certificate recorded): "axisymmetric" where ``hcell.AXISYMMETRIC_KINEMATICS``
    is nonzero (``hcell3d-axisym``), else "projected"."""
    return "axisymmetric" if parameters.get(AXISYMMETRIC_KINEMATICS, 0.0) else "projected"


def cell_kinematics(mesostructure: Mesostructure) -> str:
    """The kinematics (``KINEMATICS``) a 3D mesostructure declares (``kinematics_of`` its parameters)."""
    return kinematics_of(mesostructure.parameters)


@dataclass(frozen=True, eq=False)
class Orientations3D(OrientationSet):
    """A set of N oriented cells with weights and the matrices that localise and average
    (``orientation.OrientationSet``).

    Build it with ``orientations_3d``. Arrays are read-only.

    Attributes:
        frames: rotations R_k [-], shape (N, 3, 3), columns (n, t1, t2) in the macro frame.
        weights: w_k [-], shape (N,), summing to 1.
        localisation: L [-], shape (3 N, 6): ``(L @ d_eps).reshape(N, 3)`` is (d_eps_n, d_eps_t1,
            d_eps_t2) per cell for a macro increment d_eps (six components, ``COMPONENTS``).
        averaging: A [-], shape (6, 9 N): ``A @ moment.reshape(-1)`` is the weighted macro moment
            (six components) of per-cell moments ``moment`` of shape (N, 3, 3) in the cell frames.
        order: Lebedev order of the axes; n_spins: spins per axis; spin_period_deg: psi period [deg];
            staggered: whether the spins are staggered from axis to axis (``SPIN_STAGGER``);
            kinematics: how an increment drives the cell axes (``KINEMATICS``).
    """

    frames: np.ndarray
    order: int
    n_spins: int
    spin_period_deg: float
    staggered: bool = True
    kinematics: str = "projected"

    @property
    def axes(self) -> np.ndarray:
        """Each cell's axis n in the macro frame [-], shape (N, 3)."""
        return self.frames[:, :, 0]

    @property
    def axis_angle_deg(self) -> np.ndarray:
        """Angle between each cell axis and macro axis 1, in [0, 90] [deg], shape (N,)."""
        return np.degrees(np.arccos(np.clip(np.abs(self.frames[:, 0, 0]), 0.0, 1.0)))


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
        kinematics: "projected" or "axisymmetric" (``KINEMATICS``, module docstring).
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
    weights = np.repeat(axis_weights / n_spins, n_spins)
    count = frames.shape[0]
    loc = np.empty((count, 3, 6))
    avg = np.empty((6, count, 3, 3))
    for m, (i, j) in enumerate(_INDEX):
        factor = 1.0 if i == j else 2.0
        loc[:, :, m] = factor * frames[:, i, :] * frames[:, j, :]
        avg[m] = 0.5 * (frames[:, i, :, None] * frames[:, j, None, :] + frames[:, j, :, None] * frames[:, i, None, :])
    avg *= weights[None, :, None, None]
    if kinematics == "axisymmetric":
        loc = np.einsum("ab,kbm->kam", AXISYMMETRIC_MAP, loc)
    arrays = {"frames": frames, "weights": weights, "localisation": loc.reshape(3 * count, 6),
              "averaging": avg.reshape(6, 9 * count)}
    for a in arrays.values():
        a.flags.writeable = False
    return Orientations3D(**arrays, order=int(order), n_spins=n_spins, spin_period_deg=float(spin_period_deg),
                          staggered=bool(staggered), kinematics=kinematics)


def to_tensor(components: np.ndarray) -> np.ndarray:
    """Symmetric 3 x 3 tensor(s) from six components (..., 6) in ``COMPONENTS`` order."""
    components = np.asarray(components, dtype=np.float64)
    tensor = np.empty(components.shape[:-1] + (3, 3))
    for m, (i, j) in enumerate(_INDEX):
        tensor[..., i, j] = components[..., m]
        tensor[..., j, i] = components[..., m]
    return tensor
