"""The spatial dimension of a cell as data: ``dimension(2)`` (planar cells, disks) and ``dimension(3)``
(spatial cells, spheres).

What the package does differently in the two dimensions and that is only data or a formula (the
components of a macro tensor, a cell's local frame, the measure of a grain and of a cell, the shape
of a tangential spring, the stress unit, the invariants p and q) is read from the ``Dimension``
record of the cell's dimension, so that the code around it is one path for both.

Macro tensors are given by their Voigt components (``Dimension.components``; tensor, not
engineering, shear strains). Sign convention: compression and contraction positive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from warp_hcell.core.parameters import ALPHA_MIN_3D_DEG


def _deviator_planar(stress: np.ndarray) -> np.ndarray:
    """q = sigma11 - sigma22 [N/m] of planar stresses (..., 3)."""
    return stress[..., 0] - stress[..., 1]


def _deviator_spatial(stress: np.ndarray) -> np.ndarray:
    """q = sqrt(3 J2) [Pa] of spatial stresses (..., 6): J2 = ((s11 - s22)^2 + (s22 - s33)^2 +
    (s33 - s11)^2) / 6 + s23^2 + s13^2 + s12^2."""
    s11, s22, s33, s23, s13, s12 = (stress[..., m] for m in range(6))
    J2 = ((s11 - s22) ** 2 + (s22 - s33) ** 2 + (s33 - s11) ** 2) / 6.0 + (s23**2 + s13**2 + s12**2)
    return np.sqrt(3.0 * J2)


@dataclass(frozen=True)
class Dimension:
    """What differs between planar and spatial cells, as data and formulas (``dimension(d)``)."""

    dim: int
    """The spatial dimension d, 2 or 3."""
    components: tuple[str, ...]
    """Names of a macro tensor's Voigt components, normal ones first: (11, 22, 12) or (11, 22, 33, 23,
    13, 12)."""
    index: tuple[tuple[int, int], ...]
    """(i, j) of each component, 0-based."""
    frame: tuple[str, ...]
    """Names of a cell's local axes: (n, t) or (n, t1, t2); index 0 is the cell axis n."""
    measure: str
    """"area" (planar cells, per unit thickness) or "volume"."""
    stress_unit: str
    """Unit of a stress: "N/m" (force per unit thickness over length) or "Pa"."""
    spring_shape: tuple[int, ...]
    """Shape of one pair's tangential spring force: () in the plane (a scalar along w = (-u_t, u_n)),
    (3,) in space."""
    every_axis: str
    """How a message names all d normal components ("both", "all three")."""
    grain_measure: Callable[[np.ndarray], np.ndarray]
    """Grain radii [m] -> the measure whose density gives a grain's mass: pi r^2 [m^2] or 4/3 pi r^3
    [m^3]."""
    deviator: Callable[[np.ndarray], np.ndarray]
    """Voigt stresses (..., n_voigt) -> q: sigma11 - sigma22 [N/m] in the plane, sqrt(3 J2) [Pa] in
    space."""
    shear_strain_factor: float
    """A material point's shear strain per tensor shear component: 2 in the plane (engineering gamma12 =
    2 eps12), 1 in space."""
    boundary: str
    """The outer boundary whose measure is V_cell: "polygon" (grain indices in order) or "polyhedron"
    (outward triangles)."""
    boundary_faces: int
    """Least number of faces of a valid boundary: 1 (the polygon) or 4 (triangles)."""
    boundary_rule: str
    """What a valid boundary needs, as an error message says it."""
    empty_boundary: str
    """How an error message says that the boundary has no measure."""
    spring: str
    """What a pair's tangential spring force is, as the learning state describes it."""
    planar: bool
    """The cells are planar (disks per unit thickness), where contact laws of spheres do not apply."""
    undrained_lateral: Callable[[float], float]
    """Axial strain increment d [-] -> the lateral increment of each lateral normal component that keeps
    it undrained: -d in the plane, 1 - 1 / sqrt(1 - d) in space (volume kept exactly)."""
    isochoric_test: str
    """Name of the test that keeps the volume: "constant-volume" (biaxial) or "undrained" (triaxial)."""
    min_opening_deg: float | None
    """Least initial opening angle alpha0 [deg] the cell's closed form takes; None: no floor."""

    @property
    def n_voigt(self) -> int:
        """Number of Voigt components of a symmetric macro tensor: 3 or 6."""
        return len(self.components)

    @property
    def normal_components(self) -> tuple[str, ...]:
        """Names of the d normal components, (11, 22) or (11, 22, 33): those a loading step controls."""
        return self.components[: self.dim]

    def mean_stress(self, stress: np.ndarray) -> np.ndarray:
        """p = tr(sigma) / d [N/m or Pa] of Voigt stresses (..., n_voigt), compression positive."""
        total = stress[..., 0]
        for a in range(1, self.dim):
            total = total + stress[..., a]
        return total / self.dim

    def to_tensor(self, components: np.ndarray) -> np.ndarray:
        """Symmetric d x d tensor(s) (..., d, d) from Voigt components (..., n_voigt)."""
        components = np.asarray(components, dtype=np.float64)
        tensor = np.empty(components.shape[:-1] + (self.dim, self.dim))
        for m, (i, j) in enumerate(self.index):
            tensor[..., i, j] = components[..., m]
            tensor[..., j, i] = components[..., m]
        return tensor


_DIMENSIONS = {
    2: Dimension(2, ("11", "22", "12"), ((0, 0), (1, 1), (0, 1)), ("n", "t"), "area", "N/m", (), "both",
                 lambda radius: math.pi * radius**2, _deviator_planar, 2.0,
                 boundary="polygon", boundary_faces=1, boundary_rule="outer polygon needs >= 3 distinct grains",
                 empty_boundary="polygon has zero area",
                 spring="tangential spring force of each pair, on grain i along w = (-u_t, u_n), "
                        "u = (x_j - x_i) / |x_j - x_i|; zero out of contact",
                 planar=True, undrained_lateral=lambda d: -d, isochoric_test="constant-volume", min_opening_deg=None),
    3: Dimension(3, ("11", "22", "33", "23", "13", "12"), ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)),
                 ("n", "t1", "t2"), "volume", "Pa", (3,), "all three",
                 lambda radius: 4.0 / 3.0 * math.pi * radius**3, _deviator_spatial, 1.0,
                 boundary="polyhedron", boundary_faces=4,
                 boundary_rule="outer surface needs >= 4 triangles of distinct grains",
                 empty_boundary="surface encloses no volume",
                 spring="tangential spring force vector of each pair on grain i, components (n, t1, t2), in the "
                        "contact's tangent plane (normal u = (x_j - x_i) / |x_j - x_i|); zero out of contact",
                 planar=False, undrained_lateral=lambda d: 1.0 - 1.0 / math.sqrt(1.0 - d),
                 isochoric_test="undrained", min_opening_deg=ALPHA_MIN_3D_DEG),
}


def dimension(dim: int) -> Dimension:
    """The ``Dimension`` record of ``dim``.

    Raises:
        ValueError: ``dim`` is neither 2 nor 3.
    """
    try:
        return _DIMENSIONS[int(dim)]
    except KeyError:
        raise ValueError(f"dimension {dim} is neither 2 nor 3") from None
