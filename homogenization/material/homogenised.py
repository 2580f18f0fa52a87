"""The homogenised H-model as a material: stress and consistent tangent of a batch of material points.

``HomogenisedMaterial(cell_model, orient, mesostructure, n_points)`` holds, for each of
``n_points`` material points (e.g. finite-element Gauss points), its own set of oriented cells
(``orient``: frames R_k with weights w_k), built from the point's mesostructure. ``update(state, d_e)`` advances every point by its own
macro strain increment with ONE batched ``cell_model.step`` call over all points' cells and
returns the new state, the stresses and the consistent tangents. Like ``step``, ``update``
is pure: trial increments (Newton iterations of a stress control or of a finite-element
solve) start again from the same saved state.

Voigt form in the macro frame, of the dimension d of the cells (``warp_hcell.core.dimension``): in
the plane e = (eps11, eps22, gamma12), gamma12 = 2 eps12 [-] (engineering shear, as plane-strain
finite elements take it) and sigma = (sigma11, sigma22, sigma12) [N/m]; in space e = (eps11, eps22,
eps33, eps23, eps13, eps12) (tensor shear) [-] and sigma in [Pa]. Sign convention: compression and
contraction positive.

Localisation (spec sections 3, 13): cell k with frame R_k gets the normal strains along its axes,
L_k d_e, shear of the cell dropped (``orientation``). Stress: sigma = sum_k w_k R_k S_k R_k^T / V with
the volume rule V = V0 J (``orientation.VOLUME_RULE``), J multiplied by prod_a (1 - d_eps_aa) per
increment. Tangent: D = d sigma / d(d_e) = ::

    (1/V) sum_k w_k A_k C_k L_k + sigma (x) (1/(1 - d_eps_aa) for a = 1..d, 0 for the shears),

A_k the macro components of R_k e_a e_a R_k^T and C_k the cell tangent d(S_aa)/d(d_eps_b) of the
increment (the last term is -sigma (x) dV/d(d_e) / V). The cell moment's off-diagonal terms (zero
for the H-cells) enter the stress but not the tangent.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization.material import orientation as orient_mod
from warp_hcell.core.contract import CellModel
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.mesostructure import Mesostructure, per_cell

COMPILED_TANGENT_FROM_CELLS = 8192
"""Spatial batches of at least this many cells (points x orientations) average their tangents with the compiled
``tangent_average.average``, smaller ones with its two einsums, whose time there is below numba's start-up (a
speed setting: both give the same bits)."""


@dataclass(frozen=True)
class MaterialState:
    """State of a batch of material points (a value: ``update`` returns a new one).

    Attributes:
        cells: cell-model state of all n_points * n_orientations cells, point-major (cell
            p * n_orientations + k is orientation k of point p).
        J: volume ratio V / V0 [-], shape (n_points,).
        strain: accumulated macro strain [-], shape (n_points, n_voigt) (module docstring), the
            sum of the increments, compression positive.
        stress: macro stress [N/m or Pa], shape (n_points, n_voigt), compression positive.
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
        stress: macro stress [N/m or Pa], shape (n_points, n_voigt), compression positive.
        tangent: d stress / d(d_e) [N/m or Pa], shape (n_points, n_voigt, n_voigt); None when
            not asked for.
        diagnostics: the backend's diagnostics of the one ``step`` call.
    """

    state: MaterialState
    stress: np.ndarray
    tangent: np.ndarray | None
    diagnostics: Mapping[str, float] = field(default_factory=dict)


class HomogenisedMaterial:
    """A batch of H-model material points of dimension d (module docstring), d that of ``orient``.

    Args:
        cell_model: any ``CellModel`` of cells of dimension d; ``update(..., with_tangent=True)``
            needs one whose step takes ``with_tangent`` (ValueError otherwise); plain updates call
            ``step`` without it.
        orient: orientations and fabric weights shared by every point (``orientation.orientations``
            or ``orientation.orientations_3d``).
        mesostructure: the cell of every point, or a sequence of n_points, one per point (a
            weaker zone of a specimen has its own, e.g. an H-cell of larger alpha0), all of one
            topology and of dimension d; every cell of a point starts from the point's
            mesostructure.
        n_points: number of material points.

    Raises:
        ValueError: n_points < 1, or a mesostructure of another dimension than ``orient``.
    """

    def __init__(self, cell_model: CellModel, orient: orient_mod.OrientationSet,
                 mesostructure: Mesostructure | Sequence[Mesostructure], n_points: int) -> None:
        if int(n_points) < 1:
            raise ValueError(f"n_points = {n_points} must be >= 1")
        self.model = cell_model
        self.orient = orient
        self.n_points = int(n_points)
        self.mesostructures, self.point_mesostructure = per_cell(mesostructure, self.n_points)
        """Distinct mesostructures, and the index of each point's one, shape (n_points,)."""
        self.space = dimension(orient.frames.shape[1])
        """The ``Dimension`` of the points and their cells."""
        self.dim, self.n_voigt = self.space.dim, self.space.n_voigt
        for meso in self.mesostructures:
            if meso.dim != self.dim:
                raise ValueError(f"mesostructure {meso.name!r} has dimension {meso.dim}; "
                                 f"a material of dimension {self.dim} needs cells of dimension {self.dim}")
        n = orient.n_cells
        self.L = np.array(orient.localisation).reshape(n, self.dim, self.n_voigt)
        """L_k [-], shape (N, dim, n_voigt): the cell's normal strains = L_k @ d_e."""
        self.L[:, :, self.dim:] /= self.space.shear_strain_factor
        self.A = np.ascontiguousarray(np.diagonal(orient.averaging.reshape(self.n_voigt, n, self.dim, self.dim),
                                                  axis1=2, axis2=3))
        """w_k A_k [-], shape (n_voigt, N, dim): macro components of w_k R_k e_a e_a R_k^T."""
        self.V0 = np.zeros(self.n_points)
        self.returns_tangent = "with_tangent" in inspect.signature(cell_model.step).parameters
        """Whether the backend's step takes ``with_tangent`` (plain updates work without it)."""

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
        self.V0 = (volume * self.orient.weights).sum(axis=1)  # per point (BLAS's order depends on n_points)
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
            tangent = self._macro_tangent(response.tangent, stress, d_e, V)
        new = MaterialState(cells, J, state.strain + d_e, stress)
        return MaterialUpdate(new, stress, tangent, dict(response.diagnostics))

    @property
    def defers_tangent(self) -> bool:
        """Whether the cell model gives a step's tangent apart from the step (``step_tangent(old_cells,
        new_cells)``): then ``tangent`` after a plain ``update`` costs no second step."""
        return callable(getattr(self.model, "step_tangent", None))

    def tangent(self, state: MaterialState, d_e: np.ndarray, update: MaterialUpdate) -> np.ndarray:
        """The tangent ``update(state, d_e, with_tangent=True)`` returns, of ``update`` = ``update(state, d_e,
        with_tangent=False)`` [N/m or Pa], shape (n_points, n_voigt, n_voigt); needs ``defers_tangent``."""
        d_e = np.asarray(d_e, dtype=np.float64).reshape(self.n_points, self.n_voigt)
        C = self.model.step_tangent(state.cells, update.state.cells)
        return self._macro_tangent(C, update.stress, d_e, self.V0 * update.state.J)

    def _macro_tangent(self, cell_tangent: np.ndarray, stress: np.ndarray, d_e: np.ndarray,
                       V: np.ndarray) -> np.ndarray:
        """D (module docstring) of the cells' tangents (n_cells, dim, dim), the stress and d_e of the
        increment and the volumes V at its end, shapes (n_points, n_voigt) and (n_points,)."""
        C = np.asarray(cell_tangent).reshape(self.n_points, self.orient.n_cells, self.dim, self.dim)
        tangent = self._cell_tangent_average(C) / V[:, None, None]
        volume = np.zeros((self.n_points, self.n_voigt))
        volume[:, :self.dim] = 1.0 / (1.0 - d_e[:, :self.dim])
        tangent += stress[:, :, None] * volume[:, None, :]
        return tangent

    def stress_of(self, cells: Any, J: np.ndarray) -> np.ndarray:
        """Macro stress [N/m or Pa], shape (n_points, n_voigt), of ``cells`` (a state of this material's cells)
        at volume ratios ``J`` (n_points,), as ``update`` averages it (e.g. after cells were replaced)."""
        V = self.V0 * np.asarray(J, dtype=np.float64)
        moment = np.ascontiguousarray(self.model.response(cells).moment).reshape(self.n_points,
                                                                               self.dim * self.dim * self.orient.n_cells)
        return np.einsum("pm,im->pi", moment, self.orient.averaging) / V[:, None]

    def _cell_tangent_average(self, C: np.ndarray) -> np.ndarray:
        """sum_k w_k A_k C_k L_k [N/m or Pa], shape (n_points, n_voigt, n_voigt), of C (n_points, N, dim, dim).

        Per-point products, so a point's tangent does not depend on its batch. The two dimensions sum
        the same terms in different orders (a stacked matmul, two einsums); each order is kept because the
        runs' files are pinned to it bit for bit. In space, batches of ``COMPILED_TANGENT_FROM_CELLS``
        cells or more take ``tangent_average.average``, the einsums' bits in a compiled loop.
        """
        n = self.orient.n_cells
        if self.dim == 2:
            CL = C[..., :, 0, None] * self.L[None, :, 0, None, :] + C[..., :, 1, None] * self.L[None, :, 1, None, :]
            return self.A.reshape(self.n_voigt, n * self.dim) @ CL.reshape(self.n_points, n * self.dim, self.n_voigt)
        if self.n_points * n >= COMPILED_TANGENT_FROM_CELLS:
            from homogenization.material.tangent_average import average  # noqa: PLC0415 (loads numba)

            out = np.empty((self.n_points, self.n_voigt, self.n_voigt))
            average(np.ascontiguousarray(C, dtype=np.float64), self.L, self.A, out)
            return out
        CL = np.einsum("pkab,kbj->pkaj", C, self.L)
        return np.einsum("ika,pkaj->pij", self.A, CL)
