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
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from homogenization import orientation as orient_mod
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


class HomogenisedMaterial:
    """A batch of H-model material points, each with its own cells (see the module docstring).

    Args:
        cell_model: any ``CellModel``; ``update(..., with_tangent=True)`` needs one whose step
            takes ``with_tangent`` (ValueError otherwise); plain updates call ``step`` without it.
        orient: orientations and fabric weights shared by every point.
        mesostructure: the cell of every point, or a sequence of n_points, one per point (a
            weaker zone of a specimen has its own, e.g. an H-cell of larger alpha0), all of one
            topology; every cell of a point starts from the point's mesostructure.
        n_points: number of material points.
    """

    def __init__(self, cell_model: CellModel, orient: orient_mod.Orientations,
                 mesostructure: Mesostructure | Sequence[Mesostructure], n_points: int) -> None:
        if int(n_points) < 1:
            raise ValueError(f"n_points = {n_points} must be >= 1")
        self.model = cell_model
        self.orient = orient
        self.n_points = int(n_points)
        self.mesostructures, self.point_mesostructure = per_cell(mesostructure, self.n_points)
        """Distinct mesostructures, and the index of each point's one, shape (n_points,)."""
        self.G = voigt_localisation(orient)
        self.wGT = np.ascontiguousarray((orient.weights[:, None, None] * self.G).reshape(-1, 3).T)
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
        area = self.model.response(cells).area.reshape(self.n_points, n)
        self.V0 = area @ self.orient.weights
        zeros = np.zeros((self.n_points, 3))
        return MaterialState(cells, np.ones(self.n_points), zeros, zeros.copy())

    def localise(self, d_e: np.ndarray) -> np.ndarray:
        """Per-cell (d_eps_n, d_eps_t) [-], shape (n_cells, 2), of Voigt increments d_e (n_points, 3)."""
        return np.einsum("kai,pi->pka", self.G, d_e).reshape(self.n_cells, 2)

    def update(self, state: MaterialState, d_e: np.ndarray, *, with_tangent: bool = True) -> MaterialUpdate:
        """Advance every point by its macro strain increment (one batched cell step); pure.

        Args:
            state: the material state at the start of the increment.
            d_e: (d_eps11, d_eps22, d_gamma12) [-], shape (n_points, 3), compression positive.
            with_tangent: also return the consistent tangent.

        Returns:
            The ``MaterialUpdate``.
        """
        d_e = np.asarray(d_e, dtype=np.float64).reshape(self.n_points, 3)
        d_local = self.localise(d_e)
        if with_tangent:
            if not self.returns_tangent:
                raise ValueError(f"cell model {getattr(self.model, 'name', self.model)!r} returns no consistent "
                                 f"tangent (its step takes no with_tangent)")
            cells, response = self.model.step(state.cells, d_local, with_tangent=True)
        else:
            cells, response = self.model.step(state.cells, d_local)
        n = self.orient.n_cells
        factor = (1.0 - d_e[:, 0]) * (1.0 - d_e[:, 1])
        J = state.J * factor
        V = self.V0 * J
        moment = np.ascontiguousarray(response.moment).reshape(self.n_points, 4 * n)
        # einsum without BLAS: a point's stress does not depend on the batch, bit for bit
        stress = np.einsum("pm,im->pi", moment, self.orient.averaging) / V[:, None]
        tangent = None
        if with_tangent:
            if response.tangent is None:
                raise ValueError(f"cell model {getattr(self.model, 'name', self.model)!r} returned no tangent")
            C = response.tangent.reshape(self.n_points, n, 2, 2)
            # C_k G_k, then the weighted sum of G_k^T (.) over cells and components as one
            # stacked matmul per point (per-point products: batch invariant)
            CG = C[..., :, 0, None] * self.G[None, :, 0, None, :] + C[..., :, 1, None] * self.G[None, :, 1, None, :]
            tangent = self.wGT @ CG.reshape(self.n_points, 2 * n, 3) / V[:, None, None]
            volume = np.zeros((self.n_points, 3))
            volume[:, 0] = 1.0 / (1.0 - d_e[:, 0])
            volume[:, 1] = 1.0 / (1.0 - d_e[:, 1])
            tangent += stress[:, :, None] * volume[:, None, :]
        new = MaterialState(cells, J, state.strain + d_e, stress)
        return MaterialUpdate(new, stress, tangent, dict(response.diagnostics))
