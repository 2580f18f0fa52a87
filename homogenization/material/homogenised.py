"""The homogenised H-model as a material: stress and consistent tangent of a batch of material points.

``HomogenisedMaterial(cell_model, orient, mesostructure, n_points)`` holds, for each of
``n_points`` material points (e.g. finite-element Gauss points), its own set of oriented cells
(``orient``: theta_k with weights w_k), built from the point's mesostructure. ``update(state, d_e)`` advances every point by its own
macro strain increment with ONE batched ``cell_model.step`` call over all points' cells and
returns the new state, the stresses and the consistent tangents. Like ``step``, ``update``
is pure: trial increments (Newton iterations of a stress control or of a finite-element
solve) start again from the same saved state.

Plane strain, Voigt form, in the macro frame (axes 1, 2)::

    e = (eps11, eps22, gamma12), gamma12 = 2 eps12 [-];  sigma = (sigma11, sigma22, sigma12) [N/m].

Sign convention: compression and contraction positive.

Localisation (spec sections 3, 13): cell k at theta_k gets d_eps_n = P_k . d_e and
d_eps_t = Q_k . d_e with P_k = (c^2, s^2, s c), Q_k = (s^2, c^2, -s c); shear of the cell is
dropped. Stress: sigma = sum_k w_k R_k S_k R_k^T / V with the volume rule V = V0 J
(``orientation.VOLUME_RULE``), J multiplied by (1 - d_eps11)(1 - d_eps22) per increment.
Tangent: D = d sigma / d(d_e) = ::

    (1/V) sum_k w_k [P_k; Q_k]^T C_k [P_k; Q_k] + sigma (x) (1/(1 - d_eps11), 1/(1 - d_eps22), 0),

with C_k = d(S_nn, S_tt)/d(d_eps_n, d_eps_t) the cell tangent of the increment (the last term
is -sigma (x) dV/d(d_e) / V). The cell moment's S_nt (zero for the H-cell) enters the stress but
not the tangent.

In 3D (``HomogenisedMaterial3D``, cells of dimension 3 oriented by
``homogenization.material.orientation``) the macro tensors have six components (11, 22, 33, 23, 13, 12)
(tensor shear strains, not engineering ones) [-] and [Pa]; cell k with frame R_k = (n, t1, t2) gets
(d_eps_n, d_eps_t1, d_eps_t2) = L_k d_e (normal strains along its axes, shear dropped), and
sigma = sum_k w_k R_k S_k R_k^T / V, V = V0 J, J multiplied by (1 - d_eps11)(1 - d_eps22)(1 - d_eps33)
per increment. Tangent: D = (1/V) sum_k w_k A_k C_k L_k + sigma (x) (1/(1 - d_eps_aa), a = 1..3; 0, 0, 0),
A_k [6 x 3] the macro components of R_k e_a e_a R_k^T and C_k = d(S_nn, S_t1t1, S_t2t2)/d(d_eps_n,
d_eps_t1, d_eps_t2) the cell tangent (off-diagonal moments enter the stress, not the tangent).
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization.material import orientation as orient_mod
from warp_hcell.core.contract import CellModel
from warp_hcell.mesostructures.mesostructure import Mesostructure, per_cell


@dataclass(frozen=True)
class MaterialState:
    """State of a batch of material points (a value: ``update`` returns a new one).

    Attributes:
        cells: cell-model state of all n_points * n_orientations cells, point-major (cell
            p * n_orientations + k is orientation k of point p).
        J: volume ratio V / V0 [-], shape (n_points,).
        strain: accumulated macro strain (eps11, eps22, gamma12) [-], shape (n_points, 3),
            the sum of the increments, compression positive.
        stress: (sigma11, sigma22, sigma12) [N/m], shape (n_points, 3), compression positive.
    """

    cells: Any
    J: np.ndarray
    strain: np.ndarray
    stress: np.ndarray


@dataclass(frozen=True)
class MaterialUpdate:
    """Result of ``HomogenisedMaterial.update``.

    Attributes:
        state: the material state at the end of the increment.
        stress: (sigma11, sigma22, sigma12) [N/m], shape (n_points, 3), compression positive.
        tangent: d stress / d(d_eps11, d_eps22, d_gamma12) [N/m], shape (n_points, 3, 3);
            None when not asked for.
        diagnostics: the backend's diagnostics of the one ``step`` call.
    """

    state: MaterialState
    stress: np.ndarray
    tangent: np.ndarray | None
    diagnostics: Mapping[str, float] = field(default_factory=dict)


def voigt_localisation(orient: orient_mod.Orientations) -> np.ndarray:
    """G_k = [P_k; Q_k] [-], shape (N, 2, 3): (d_eps_n, d_eps_t) = G_k @ (d_eps11, d_eps22, d_gamma12)."""
    c, s = np.cos(orient.theta), np.sin(orient.theta)
    G = np.empty((orient.n_cells, 2, 3))
    G[:, 0] = np.stack([c * c, s * s, s * c], axis=1)
    G[:, 1] = np.stack([s * s, c * c, -s * c], axis=1)
    return G


class _HomogenisedMaterialBase:
    """What a batch of material points does in either dimension (the module docstring).

    A subclass sets ``dim``, the number ``n_voigt`` of macro components, the localisation
    ``self.L`` [-], shape (N, dim, n_voigt), in ``_localisation`` and the averaged cell
    tangent in ``_cell_tangent_average``.

    Args:
        cell_model: any ``CellModel`` of cells of dimension ``dim``; ``update(...,
            with_tangent=True)`` needs one whose step takes ``with_tangent`` (ValueError
            otherwise); plain updates call ``step`` without it.
        orient: orientations and fabric weights shared by every point.
        mesostructure: the cell of every point, or a sequence of n_points, one per point (a
            weaker zone of a specimen has its own, e.g. an H-cell of larger alpha0), all of one
            topology and of dimension ``dim``; every cell of a point starts from the point's
            mesostructure.
        n_points: number of material points.
    """

    dim: int
    n_voigt: int

    def __init__(self, cell_model: CellModel, orient: orient_mod.OrientationSet,
                 mesostructure: Mesostructure | Sequence[Mesostructure], n_points: int) -> None:
        if int(n_points) < 1:
            raise ValueError(f"n_points = {n_points} must be >= 1")
        self.model = cell_model
        self.orient = orient
        self.n_points = int(n_points)
        self.mesostructures, self.point_mesostructure = per_cell(mesostructure, self.n_points)
        """Distinct mesostructures, and the index of each point's one, shape (n_points,)."""
        for meso in self.mesostructures:
            if getattr(meso, "dim", 2) != self.dim:
                raise ValueError(f"mesostructure {meso.name!r} has dimension {getattr(meso, 'dim', 2)}; "
                                 f"a material of dimension {self.dim} needs cells of dimension {self.dim}")
        self.L = self._localisation(orient)
        """L_k [-], shape (N, dim, n_voigt): the cell's normal strains = L_k @ d_e."""
        self.V0 = np.zeros(self.n_points)
        self.returns_tangent = "with_tangent" in inspect.signature(cell_model.step).parameters
        """Whether the backend's step takes ``with_tangent`` (plain updates work without it)."""

    def _localisation(self, orient: orient_mod.OrientationSet) -> np.ndarray:
        raise NotImplementedError

    def _cell_tangent_average(self, C: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    @property
    def n_cells(self) -> int:
        """Cells stepped per update: n_points * n_orientations."""
        return self.n_points * self.orient.n_cells

    def init_state(self) -> MaterialState:
        """Touching, force-free cells at every point; sets V0 = sum_k w_k V_cell,k per point."""
        n = self.orient.n_cells
        if len(self.mesostructures) == 1:
            cells = self.model.init_state(self.mesostructures[0], self.n_cells)
        else:
            cells = self.model.init_state([self.mesostructures[k] for k in np.repeat(self.point_mesostructure, n)],
                                          self.n_cells)
        volume = self.model.response(cells).area.reshape(self.n_points, n)
        self.V0 = volume @ self.orient.weights
        zeros = np.zeros((self.n_points, self.n_voigt))
        return MaterialState(cells, np.ones(self.n_points), zeros, zeros.copy())

    def localise(self, d_e: np.ndarray) -> np.ndarray:
        """Per-cell normal strains along the cell's axes [-], shape (n_cells, dim), of d_e (n_points, n_voigt)."""
        return np.einsum("kai,pi->pka", self.L, d_e).reshape(self.n_cells, self.dim)

    def update(self, state: MaterialState, d_e: np.ndarray, *, with_tangent: bool = True) -> MaterialUpdate:
        """Advance every point by its macro strain increment (one batched cell step); pure.

        Args:
            state: the material state at the start of the increment.
            d_e: macro strain increments [-], shape (n_points, n_voigt), compression positive
                (2D: (d_eps11, d_eps22, d_gamma12); 3D: (d_eps11, d_eps22, d_eps33, d_eps23,
                d_eps13, d_eps12), tensor shear components).
            with_tangent: also return the consistent tangent d sigma / d(d_e), shape
                (n_points, n_voigt, n_voigt).

        Returns:
            The ``MaterialUpdate``.
        """
        d_e = np.asarray(d_e, dtype=np.float64).reshape(self.n_points, self.n_voigt)
        d_local = self.localise(d_e)
        if with_tangent:
            if not self.returns_tangent:
                raise ValueError(f"cell model {getattr(self.model, 'name', self.model)!r} returns no consistent "
                                 f"tangent (its step takes no with_tangent)")
            cells, response = self.model.step(state.cells, d_local, with_tangent=True)
        else:
            cells, response = self.model.step(state.cells, d_local)
        n = self.orient.n_cells
        factor = 1.0 - d_e[:, 0]
        for a in range(1, self.dim):
            factor = factor * (1.0 - d_e[:, a])
        J = state.J * factor
        V = self.V0 * J
        moment = np.ascontiguousarray(response.moment).reshape(self.n_points, self.dim * self.dim * n)
        # einsum without BLAS: a point's stress does not depend on the batch, bit for bit
        stress = np.einsum("pm,im->pi", moment, self.orient.averaging) / V[:, None]
        tangent = None
        if with_tangent:
            if response.tangent is None:
                raise ValueError(f"cell model {getattr(self.model, 'name', self.model)!r} returned no tangent")
            C = np.asarray(response.tangent).reshape(self.n_points, n, self.dim, self.dim)
            tangent = self._cell_tangent_average(C) / V[:, None, None]
            volume = np.zeros((self.n_points, self.n_voigt))
            volume[:, :self.dim] = 1.0 / (1.0 - d_e[:, :self.dim])
            tangent += stress[:, :, None] * volume[:, None, :]
        new = MaterialState(cells, J, state.strain + d_e, stress)
        return MaterialUpdate(new, stress, tangent, dict(response.diagnostics))


class HomogenisedMaterial(_HomogenisedMaterialBase):
    """A batch of plane-strain H-model material points (module docstring); Voigt components.

    Args: those of ``_HomogenisedMaterialBase``, with ``orient`` an ``orientation.Orientations``.
    """

    dim = 2
    """Spatial dimension: plane strain, three Voigt components."""
    n_voigt = 3

    def _localisation(self, orient: orient_mod.Orientations) -> np.ndarray:
        G = voigt_localisation(orient)
        self.wGT = np.ascontiguousarray((orient.weights[:, None, None] * G).reshape(-1, 3).T)
        """w_k G_k^T stacked over cells and components [-], shape (3, 2 N)."""
        return G

    def _cell_tangent_average(self, C: np.ndarray) -> np.ndarray:
        """sum_k w_k G_k^T C_k G_k [N/m], shape (n_points, 3, 3), of C (n_points, N, 2, 2)."""
        G = self.L
        # C_k G_k, then the weighted sum of G_k^T (.) over cells and components as one
        # stacked matmul per point (per-point products: batch invariant)
        CG = C[..., :, 0, None] * G[None, :, 0, None, :] + C[..., :, 1, None] * G[None, :, 1, None, :]
        return self.wGT @ CG.reshape(self.n_points, 2 * self.orient.n_cells, 3)


class HomogenisedMaterial3D(_HomogenisedMaterialBase):
    """A batch of 3D H-model material points (module docstring); six tensor components.

    Args: those of ``_HomogenisedMaterialBase``, with ``orient`` an
    ``orientation.Orientations3D`` and cells of dimension 3 (local strains (n_cells, 3),
    moments (n_cells, 3, 3), volume [m^3] in ``response.area``).
    """

    dim = 3
    """Spatial dimension: six tensor components."""
    n_voigt = 6

    def _localisation(self, orient: orient_mod.Orientations3D) -> np.ndarray:
        n = orient.n_cells
        self.A = np.ascontiguousarray(np.diagonal(orient.averaging.reshape(6, n, 3, 3), axis1=2, axis2=3))
        """w_k A_k [-], shape (6, N, 3): macro components of w_k R_k e_a e_a R_k^T."""
        return orient.localisation.reshape(n, 3, 6)

    def _cell_tangent_average(self, C: np.ndarray) -> np.ndarray:
        """sum_k w_k A_k C_k L_k [Pa], shape (n_points, 6, 6), of C (n_points, N, 3, 3)."""
        CL = np.einsum("pkab,kbj->pkaj", C, self.L)
        return np.einsum("ika,pkaj->pij", self.A, CL)
