"""The cell-model protocol shared by the analytical, DEM and ANN backends.

This module sits at the bottom of the package (``warp_hcell.core``): ``warp_hcell``,
``training`` and ``homogenization`` all import it, and it imports none of them.

A cell model creates a batch of independent cells (one per orientation, or one per
database probe) from a mesostructure (``warp_hcell.mesostructures.mesostructure.Mesostructure``: a builder
such as ``h_cell(alpha0_deg, radius)`` or a spec of ``warp_hcell.mesostructures.builders``, or a file),
advances them by per-cell strain increments given in each cell's local frame, and returns the
Love-Weber moment S and the cell measure V_cell. The homogenisation drives any cell model through
this protocol without knowing which backend it is; backends know nothing about orientations,
weights or loading programmes.

Every shape below holds for cells of either dimension d = ``mesostructure.dim`` (2: planar cells
of disks, per unit thickness; 3: spatial cells of spheres; ``warp_hcell.core.dimension``).
Sign convention: compression and contraction positive (strain increments, forces, S).
Local frame: index 0 = n (cell axis), then the lateral axes: t (d = 2) or t1, t2 (d = 3).

States are values: ``step`` never modifies its input state, so saving a state is keeping a
reference to it, and a trial increment (stress control) is a ``step`` whose result is
discarded. ``take`` gathers cells (with repetition) to restore saved cells or fan a state
out into probes; ``state_to_arrays``/``state_from_arrays`` round-trip a state through
named numpy arrays (HDF5 snapshots, resume).

Tangents: ``step(state, d_eps_local, with_tangent=True)`` also returns, in
``CellResponse.tangent``, the consistent cell tangent C = d(diagonal of S)/d(eps along the
local axes) [N m], shape (n_cells, d, d), of the increment just taken (the derivative of the step's result with respect to its
own increment, in the contact regimes the step reached: stick, slide, open). A backend
computes it only when asked, so plain calls cost nothing extra.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol, Sequence, TypeVar, runtime_checkable

import numpy as np

from warp_hcell.core.dimension import dimension

Mesostructure = Any
"""A ``warp_hcell.mesostructures.mesostructure.Mesostructure`` (that layer sits above this one)."""
S = TypeVar("S")


@dataclass(frozen=True)
class CellResponse:
    """Meso-stress output of a batch of cells.

    Attributes:
        moment: Love-Weber sum S = sum_c f_c (x) l_c over the contacts [N m], shape
            (n_cells, d, d), local frame, compression positive. sigma_cell = moment / area.
        area: cell measure V_cell, shape (n_cells,): the area [m^2] of the polygon (d = 2)
            or the volume [m^3] of the polyhedron (d = 3) through the centres of the
            driven (outer) grains, as the mesostructure declares them.
        diagnostics: per-call scalars a backend may report (e.g. DEM ``substeps`` spent
            and ``n_unconverged`` cells); empty for closed-form backends.
        tangent: consistent cell tangent d(S_aa)/d(eps_b) [N m] of the increment just
            taken (a, b local axes), shape (n_cells, d, d), compression positive; None
            where the backend was not asked for it.
    """

    moment: np.ndarray
    area: np.ndarray
    diagnostics: Mapping[str, float] = field(default_factory=dict)
    tangent: np.ndarray | None = None


@runtime_checkable
class CellModel(Protocol[S]):
    """What the homogenisation needs from a cell backend.

    Implementations are constructed with the physical parameters (a
    ``warp_hcell.core.parameters.ContactLaw``, the grain radius [m], which only the closed-form
    analytical cell uses: the others take every radius from the mesostructure) and
    keyword-only numerical options; see ``homogenization.backends.make_cell_model``. The cells
    themselves come from a mesostructure, in ``init_state``.
    """

    name: str
    """Backend name as used by ``--backend``."""

    def init_state(self, mesostructure: Mesostructure | Sequence[Mesostructure], n_cells: int) -> S:
        """Touching, force-free cells built from a mesostructure.

        Args:
            mesostructure: the cell every cell of the batch starts from, or a sequence of
                ``n_cells`` mesostructures, one per cell (e.g. material points of different
                initial geometry), all of one topology (pairs, driven mask, outer polygon).
            n_cells: number of cells in the batch.

        Raises:
            ValueError: (one line) a mesostructure this backend does not model (the
                analytical backend models the H-cell of equal grains only; an ANN model only
                the mesostructure it was trained on), or a sequence of the wrong length.
        """
        ...

    def step(self, state: S, d_eps_local: np.ndarray, *, with_tangent: bool = False) -> tuple[S, CellResponse]:
        """Advance every cell by its own strain increment; pure (``state`` untouched).

        Args:
            state: cells before the increment.
            d_eps_local: normal strain increments along the local axes [-], shape
                (n_cells, d): (d_eps_n, d_eps_t) or (d_eps_n, d_eps_t1, d_eps_t2), compression
                positive: the cell size along axis a, l_a <- l_a (1 - d_eps_a).
            with_tangent: also return ``CellResponse.tangent``, the consistent tangent
                d(S_aa)/d(d_eps_b) [N m] of this increment, shape (n_cells, d, d) (row =
                stress component, column = strain component); None (and no extra work)
                when False.

        Returns:
            The new state and its meso-stress response.
        """
        ...

    def response(self, state: S) -> CellResponse:
        """Meso-stress of ``state`` without advancing it (e.g. the initial state)."""
        ...

    def observables(self, state: S) -> dict[str, np.ndarray]:
        """Named per-cell quantities, each of shape (n_cells,).

        Planar H-cell backends return at least ``l1, l2, d1, d2`` [m], ``alpha_deg``
        [deg], ``N1, N2, T1`` [N] (compression positive, T1 > 0 resists opening),
        ``S_nn, S_tt`` [N m], ``area`` [m^2], and contact flags ``closed1, closed2``
        (bool: type-1 / type-2 contacts closed); a spatial cell's backends return those
        its mesostructure declares (``Mesostructure.observables``).
        """
        ...

    def take(self, state: S, index: np.ndarray) -> S:
        """New state made of cells ``state[index]`` (int array, repetition allowed)."""
        ...

    def state_to_arrays(self, state: S) -> dict[str, np.ndarray]:
        """Named numpy arrays (first axis n_cells) that fully describe ``state``."""
        ...

    def state_from_arrays(self, arrays: Mapping[str, Any]) -> S:
        """Inverse of ``state_to_arrays``."""
        ...


class ArrayStateMixin:
    """``take`` and the array round trip for backends whose state is a NamedTuple of arrays.

    The backend sets ``state_type`` to its NamedTuple class; every field is a float64 array
    of shape (n_cells,).
    """

    state_type: type

    def take(self, state, index: np.ndarray):
        """New state made of cells ``state[index]`` (int array, repetition allowed)."""
        index = np.asarray(index, dtype=np.intp)
        return self.state_type(*(value[index] for value in state))

    def state_to_arrays(self, state) -> dict[str, np.ndarray]:
        """Copies of the state fields, keyed by field name."""
        return {name: np.array(value, dtype=np.float64) for name, value in zip(state._fields, state)}

    def state_from_arrays(self, arrays: Mapping[str, Any]):
        """Inverse of ``state_to_arrays``; KeyError names a missing field."""
        return self.state_type(*(np.array(arrays[name], dtype=np.float64) for name in self.state_type._fields))


class CellCounts:
    """``n_grains`` and ``n_pairs`` of a cell description with ``radius`` (n_grains,) and
    ``pairs`` (n_pairs, 2), numpy arrays or torch tensors."""

    radius: Any
    pairs: Any

    @property
    def n_grains(self) -> int:
        """Number of grains."""
        return int(self.radius.shape[0])

    @property
    def n_pairs(self) -> int:
        """Number of candidate contact pairs."""
        return int(self.pairs.shape[0])


class SchemaCounts(CellCounts):
    """``CellCounts``, ``n_free``, ``dim`` and ``shear_shape`` of a schema with ``free_dofs``
    (n_free, 2): (grain, axis) and ``driven`` (n_grains, d)."""

    free_dofs: Any
    driven: Any

    @property
    def dim(self) -> int:
        """Spatial dimension d of the cell, 2 or 3 (``warp_hcell.core.dimension``)."""
        return int(self.driven.shape[1])

    @property
    def shear_shape(self) -> tuple[int, ...]:
        """Shape of one cell's tangential spring forces: ``(n_pairs, *spring_shape)`` of the cell's
        ``Dimension``: (n_pairs,) for d = 2 (a scalar along w = (-u_t, u_n) per pair),
        (n_pairs, 3) for d = 3 (a vector in the contact's tangent plane, local frame
        components, as the 3D DEM keeps it)."""
        return (self.n_pairs, *dimension(self.dim).spring_shape)

    @property
    def n_free(self) -> int:
        """Number of free DOFs."""
        return int(self.free_dofs.shape[0])


FEATURE_ROLES = {
    "driven": "imposed by the cell strain (l <- l (1 - d_eps))",
    "learned": "free-DOF coordinates: a meso-ANN predicts their increment",
    "history": "state variable carried from increment to increment (tangential spring force)",
    "derived": "follows exactly from the other features and the contact law",
}
"""Roles of the features of a learning state."""


@dataclass(frozen=True)
class StateFeature:
    """One per-cell array of the generic learning state.

    Attributes:
        names: column names (one per entry of the trailing axis, or one for a scalar).
        unit: unit of every column.
        role: one of ``FEATURE_ROLES``.
        description: what it holds, with its sign convention.
    """

    names: tuple[str, ...]
    unit: str
    role: str
    description: str


@dataclass(frozen=True, eq=False)
class StateSchema(SchemaCounts):
    """The learning state of one mesostructure: what a cell state is, DOF by DOF.

    A state is (cell size, free-DOF coordinates, per-pair tangential spring forces); every
    other feature (contact flags, normal forces, unbalanced forces on the free DOFs,
    Love-Weber moment, measure) follows from it, the reference geometry below and the contact
    law. Driven coordinates follow x = x_ref * l / l_ref. Local frame: index 0 = n, then t
    (d = 2) or t1, t2 (d = 3); the spring forces of a pair have ``shear_shape``; grain labels
    in feature names are 1-based.
    """

    free_dofs: np.ndarray
    """(grain index 0-based, local axis 0 .. d - 1) of every free DOF, shape (n_free, 2) int64,
    row-major order of ``driven == False``."""
    pairs: np.ndarray
    """Candidate contact pairs (i, j), 0-based, shape (n_pairs, 2) int64."""
    radius: np.ndarray
    """Grain radii [m], shape (n_grains,)."""
    reference_position: np.ndarray
    """Reference centres [m], shape (n_grains, d)."""
    reference_cell_size: np.ndarray
    """(l1_ref, .., ld_ref) [m], shape (d,)."""
    driven: np.ndarray
    """True where the DOF is driven, shape (n_grains, d) bool."""
    outer: np.ndarray
    """The boundary whose measure is V_cell: d = 2, the ordered grain indices of the outer polygon,
    shape (n_outer,); d = 3, the outer triangles, shape (n_faces, 3)."""
    features: Mapping[str, StateFeature]
    """Feature name -> ``StateFeature``, in storage order."""

    def of_role(self, role: str) -> tuple[str, ...]:
        """Names of the features with role ``role`` (``FEATURE_ROLES``)."""
        if role not in FEATURE_ROLES:
            raise ValueError(f"role {role!r} is not one of {', '.join(FEATURE_ROLES)}")
        return tuple(name for name, feature in self.features.items() if feature.role == role)

    def feature_json(self) -> str:
        """Features as JSON text: {name: {names, unit, role, description}}."""
        return json.dumps({name: {"names": list(f.names), "unit": f.unit, "role": f.role,
                                  "description": f.description} for name, f in self.features.items()})
