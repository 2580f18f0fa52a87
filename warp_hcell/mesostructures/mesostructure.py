"""Few-grain mesostructures of one cell: disks, driven DOFs, candidate contacts, outer polygon.

A ``Mesostructure`` is a frozen numpy description of ONE cell in its local frame
(index 0 = n, the cell axis; index 1 = t, the lateral direction). Every degree of freedom
(grain, direction) is either driven or free. A driven coordinate follows the cell strain
homothetically: x_n = x_n,ref * l1 / l1_ref and x_t = x_t,ref * l2 / l2_ref. Free
coordinates are integrated by the DEM. The outer polygon (ordered grains) has area V_cell.

Exports:

- ``Mesostructure``: the description (validated on construction), with the observables
  (``PairObservable``, ``OBSERVABLE_KINDS``) and parameters the cell declares;
  ``evaluate_observables`` evaluates them on a batch of cells.
- ``MesostructureError``: raised, with a one-line message, for invalid descriptions.
- ``state_schema(meso)``: the learning state of the cell (``warp_hcell.core.contract.StateSchema``).
- ``shares_state_schema(a, b)``: True when cells of ``b`` are states of ``a``'s schema.
- ``inside_outer(position, outer, point)``: whether a point lies inside a cell's outer boundary.
- ``per_cell(mesostructure, n_cells)``: the distinct mesostructures of a batch of cells and
  each cell's index into them (``CellModel.init_state`` takes one or one per cell).
- ``topology_arrays(meso, n_cells)``: the topology repeated per cell, for state arrays
  that must rebuild their cells (``warp_hcell.dem.cell.DemCell.state_from_arrays``).

Files and descriptions: ``warp_hcell.mesostructures.files``; builders: ``warp_hcell.mesostructures.hcell``
and the specs of ``warp_hcell.mesostructures.builders``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations
from typing import Mapping, Sequence

import numpy as np

from warp_hcell.core import libm
from warp_hcell.core.contract import CellCounts, StateFeature, StateSchema
from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import DemSettings

OBSERVABLE_KINDS = {
    "branch_angle": ("deg", "angle of the branch x_b - x_a from the cell axis n, atan2(t, n)"),
    "branch_length": ("m", "length |x_b - x_a| of the branch"),
    "normal_force": ("N", "normal force of the pair {a, b}, compression positive (>= 0)"),
    "shear_force": ("N", "tangential spring force of the pair {a, b}: the force on the grain of lower index along "
                         "w = (-u_t, u_n), u the unit branch from it to the other (the same for (a, b) swapped)"),
    "contact": ("bool", "the pair {a, b} is in contact"),
}
"""Kinds of ``PairObservable``: unit and definition (local frame, index 0 = n, 1 = t)."""


@dataclass(frozen=True)
class PairObservable:
    """A named per-cell quantity that a mesostructure declares: one kind measured on one pair.

    Attributes:
        name: the observable's name (e.g. ``N1``), unique in its mesostructure.
        kind: one of ``OBSERVABLE_KINDS``.
        grains: (a, b), 0-based grain indices; the kinds of branches measure x_b - x_a, the
            others the candidate pair {a, b}.
    """

    name: str
    kind: str
    grains: tuple[int, int]
LABEL_KEY = "pair_type"
"""Name of ``Mesostructure.pair_label`` in descriptions, files and state arrays."""


AXIS_NAMES = {dim: dimension(dim).frame for dim in (2, 3)}
"""Names of the local axes of a planar and of a spatial cell, by dimension (``Dimension.frame``)."""
SPIN_TURNS_DEG = (90.0, 180.0, 360.0)
"""Turns about the cell axis n tried, in order, by ``Mesostructure.spin_period_deg`` [deg]."""


class MesostructureError(ValueError):
    """An invalid mesostructure description; the message is one line."""


@dataclass(frozen=True, eq=False)
class Mesostructure(CellCounts):
    """One cell of a few disks (dim 2, frame (n, t)) or spheres (dim 3, frame (n, t1, t2)).

    Attributes:
        name: short description.
        radius: grain radii [m], (n_grains,), > 0; grain label = index + 1.
        position: reference centres [m], (n_grains, dim); column 0 = n, the cell axis.
        driven: True where the DOF (grain, direction) follows the cell strain, (n_grains, dim);
            False = free (integrated by the DEM).
        pairs: candidate contact pairs (i, j), i < j, 0-based, (n_pairs, 2).
        outer: the boundary whose measure is V_cell: 2D ordered polygon grain indices,
            (n_outer,); 3D outward triangles, (n_faces, 3).
        cell_size: reference cell size (l1_ref, l2_ref[, l3_ref]) [m], (dim,).
        pair_label: per-pair label of the builder or file that made the cell, (n_pairs,) int8,
            0 = none.
        observables: named per-cell quantities the cell declares (``PairObservable``).
        parameters: named scalars of the cell (e.g. ``alpha0_deg`` [deg]) copied by run records."""

    name: str
    radius: np.ndarray
    position: np.ndarray
    driven: np.ndarray
    pairs: np.ndarray
    outer: np.ndarray
    cell_size: np.ndarray
    pair_label: np.ndarray = field(default=None)  # type: ignore[assignment]
    observables: tuple[PairObservable, ...] = ()
    parameters: Mapping[str, float] = field(default_factory=dict)
    contact_tolerance: float = DemSettings.contact_tolerance
    """Allowed overlap, as a fraction of the pair's mean diameter, when validating [-]."""

    def __post_init__(self) -> None:
        radius = np.asarray(self.radius, dtype=np.float64).reshape(-1)
        position = np.asarray(self.position, dtype=np.float64)
        driven = np.asarray(self.driven)
        pairs = np.asarray(self.pairs, dtype=np.int64).reshape(-1, 2)
        outer = np.asarray(self.outer, dtype=np.int64)
        outer = outer.reshape(-1, 3) if position.ndim == 2 and position.shape[-1] == 3 else outer.reshape(-1)
        cell_size = np.asarray(self.cell_size, dtype=np.float64).reshape(-1)
        pair_label = (np.zeros(pairs.shape[0], np.int8) if self.pair_label is None
                      else np.asarray(self.pair_label, dtype=np.int8).reshape(-1))
        _validate(self.name, radius, position, driven, pairs, outer, cell_size, pair_label,
                  self.contact_tolerance)
        observables = tuple(self.observables)
        _validate_observables(self.name, observables, pairs, radius.size)
        parameters = {str(k): float(v) for k, v in dict(self.parameters).items()}
        object.__setattr__(self, "observables", observables)
        object.__setattr__(self, "parameters", parameters)
        for name, value in (("radius", radius), ("position", position), ("driven", driven.astype(bool)),
                            ("pairs", pairs), ("outer", outer), ("cell_size", cell_size),
                            ("pair_label", pair_label)):
            value = np.array(value)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def dim(self) -> int:
        """Spatial dimension: 2 (disks) or 3 (spheres)."""
        return int(self.position.shape[1])

    def pair_index(self, a: int, b: int) -> int:
        """Index of the candidate pair {a, b} (0-based grains); ValueError if it is none."""
        i, j = sorted((int(a), int(b)))
        hit = np.flatnonzero((self.pairs[:, 0] == i) & (self.pairs[:, 1] == j))
        if hit.size != 1:
            raise ValueError(f"mesostructure {self.name!r}: grains {i + 1} and {j + 1} are not a candidate pair")
        return int(hit[0])

    def spin_period_deg(self, rtol: float = 1e-9) -> float:
        """Period [deg] of a spatial cell's response in its spin about n: the first turn of
        ``SPIN_TURNS_DEG`` that maps the cell onto itself.

        A turn by psi about n moves (x_n, x_t1, x_t2) to (x_n, c x_t1 - s x_t2, s x_t1 + c x_t2);
        it maps the cell onto itself when every grain lands on a grain of the same radius
        (centres within ``rtol`` of the largest radius) whose driven directions are the turned
        ones, and the cell size is unchanged by the turn (l2 = l3 for a quarter turn). The
        ten-sphere H-cell has 90 deg; a cell whose fines or radii break the four-fold symmetry
        180 deg or 360 deg. ValueError for a planar cell.
        """
        if self.dim != 3:
            raise ValueError(f"mesostructure {self.name!r}: a spin about n is defined for spatial cells only")
        tol = rtol * float(self.radius.max())
        for turn in SPIN_TURNS_DEG[:-1]:
            quarter = turn == 90.0
            lateral = [2, 1] if quarter else [1, 2]
            if quarter and abs(self.cell_size[1] - self.cell_size[2]) > tol:
                continue
            turned = (np.stack([self.position[:, 0], -self.position[:, 2], self.position[:, 1]], axis=1) if quarter
                      else self.position * np.array([1.0, -1.0, -1.0]))
            driven = self.driven[:, [0, *lateral]]
            distance = np.linalg.norm(turned[:, None, :] - self.position[None, :, :], axis=-1)
            match = ((distance <= tol) & (self.radius[:, None] == self.radius[None, :])
                     & np.all(driven[:, None, :] == self.driven[None, :, :], axis=-1))
            if np.all(match.sum(axis=1) == 1) and np.all(match.sum(axis=0) == 1):
                return turn
        return SPIN_TURNS_DEG[-1]

    def schema(self) -> StateSchema:
        """The learning state of this cell (``state_schema``)."""
        return state_schema(self)

    def topology_key(self) -> tuple:
        """Hashable (pairs, driven) description: cells sharing it share one compiled kernel."""
        return (tuple(map(tuple, self.pairs.tolist())), tuple(map(tuple, self.driven.tolist())))


def polygon_area(position: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """Area of the polygon through ``position[..., outer, :]`` (shoelace, absolute value).

    Args:
        position: centre positions [m], shape (..., n_grains, 2).
        outer: ordered grain indices, shape (n_outer,).

    Returns:
        Area [m^2], shape (...).
    """
    p = position[..., outer, :]
    q = np.roll(p, -1, axis=-2)
    return 0.5 * np.abs(np.sum(p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1], axis=-1))


COMPILED_VOLUME_FROM_CELLS = 8192
"""Batches of at least this many cells take ``polyhedron_volume_of_rows``'s compiled loop, smaller ones its numpy
passes, whose time there is below numba's start-up (a speed setting: both give the same bits)."""


def polyhedron_volume(position: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Volume [m^3] enclosed by the triangles ``faces`` (n_faces, 3) through ``position`` (..., n_grains, 3).

    abs(sum over faces of x_a . (x_b x x_c)) / 6 (divergence theorem; the faces must close the surface), as
    ``polyhedron_volume_of_rows`` adds it.
    """
    return polyhedron_volume_of_rows(np.moveaxis(np.moveaxis(position, -1, 0), -1, 0), faces)


def polyhedron_volume_of_rows(rows: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``polyhedron_volume`` of grain centres laid out grain, then component first: ``rows`` (n_grains, 3, ...) [m].

    The triple products are added face by face in the order of ``faces`` with elementwise operations only, so a
    cell's volume does not depend on the batch or on the CPU's vector width; each face is one pass over rows of
    the batch's shape (which stay in cache, unlike (..., n_faces, 3) temporaries); batches of
    ``COMPILED_VOLUME_FROM_CELLS`` cells or more take ``volume_kernel.volume``, the same bits in a compiled loop.
    Returns [m^3], shape (...).
    """
    x = np.ascontiguousarray(rows)
    if x[0, 0].size >= COMPILED_VOLUME_FROM_CELLS:
        from warp_hcell.mesostructures.volume_kernel import volume  # noqa: PLC0415 (numba: loaded on first use)

        out = np.empty(x.shape[2:])
        corners = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        volume(x.reshape(x.shape[0], 3, -1), corners, out.reshape(-1))
        return out
    total = np.zeros(x.shape[2:])
    for i, j, k in np.asarray(faces).tolist():
        a, b, c = x[i], x[j], x[k]
        total += a[0] * (b[1] * c[2] - b[2] * c[1]) + a[1] * (b[2] * c[0] - b[0] * c[2]) + a[2] * (b[0] * c[1] - b[1] * c[0])
    return np.abs(total) / 6.0


def cell_measure(position: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """V_cell of cells: polygon area in 2D (``outer`` (n_outer,)), polyhedron volume in 3D (``outer`` (n_faces, 3))."""
    return polyhedron_volume(position, outer) if np.ndim(outer) == 2 else polygon_area(position, outer)


def _validate_observables(name, observables, pairs, n_grains) -> None:
    names = [o.name for o in observables]
    if len(set(names)) != len(names):
        raise MesostructureError(f"mesostructure {name!r}: observable names must be unique, got {names}")
    candidates = set(map(tuple, pairs.tolist()))
    for o in observables:
        a, b = o.grains
        if o.kind not in OBSERVABLE_KINDS:
            raise MesostructureError(f"mesostructure {name!r}: observable {o.name!r} has kind {o.kind!r}, not one of "
                                     f"{', '.join(OBSERVABLE_KINDS)}")
        if not (0 <= a < n_grains and 0 <= b < n_grains and a != b):
            raise MesostructureError(f"mesostructure {name!r}: observable {o.name!r} needs two grains in 1..{n_grains}")
        if not o.kind.startswith("branch") and tuple(sorted((a, b))) not in candidates:
            raise MesostructureError(f"mesostructure {name!r}: observable {o.name!r} needs the candidate pair "
                                     f"{min(a, b) + 1}-{max(a, b) + 1}")


def _validate(name, radius, position, driven, pairs, outer, cell_size, pair_label, tolerance) -> None:
    n_grains = radius.size
    if not 0.0 <= tolerance < 1e-3:
        raise MesostructureError(f"mesostructure {name!r}: contact_tolerance = {tolerance:g} is outside [0, 1e-3)")
    if n_grains < 2:
        raise MesostructureError(f"mesostructure {name!r}: needs at least 2 grains, got {n_grains}")
    bad = np.flatnonzero(~(np.isfinite(radius) & (radius > 0.0)))
    if bad.size:
        raise MesostructureError(
            f"mesostructure {name!r}: grain {bad[0] + 1} has radius {radius[bad[0]]:g}; radii must be finite and > 0")
    dim = position.shape[-1] if position.ndim == 2 else 0
    if dim not in (2, 3) or position.shape[0] != n_grains or not np.all(np.isfinite(position)):
        raise MesostructureError(f"mesostructure {name!r}: positions must be finite, shape ({n_grains}, 2) or "
                                 f"({n_grains}, 3)")
    if driven.shape != (n_grains, dim) or driven.dtype != bool:
        raise MesostructureError(f"mesostructure {name!r}: driven flags must be booleans, shape ({n_grains}, {dim})")
    if cell_size.shape != (dim,) or not np.all(np.isfinite(cell_size) & (cell_size > 0.0)):
        raise MesostructureError(f"mesostructure {name!r}: cell_size must be {('', '', 'two', 'three')[dim]} finite "
                                 f"values > 0")
    if pairs.shape[0] == 0:
        raise MesostructureError(f"mesostructure {name!r}: no candidate contact pairs")
    if pairs.min() < 0 or pairs.max() >= n_grains or np.any(pairs[:, 0] >= pairs[:, 1]):
        raise MesostructureError(f"mesostructure {name!r}: pairs must be (i, j) with 1 <= i < j <= {n_grains}")
    if len(set(map(tuple, pairs.tolist()))) != pairs.shape[0]:
        raise MesostructureError(f"mesostructure {name!r}: duplicate contact pairs")
    if pair_label.shape != (pairs.shape[0],):
        raise MesostructureError(f"mesostructure {name!r}: pair labels must be one per pair")
    cell = dimension(dim)
    faces = np.atleast_2d(outer)  # the polygon as one face, or the triangles
    if (faces.shape[0] < cell.boundary_faces or faces.shape[1] < 3 or outer.min() < 0 or outer.max() >= n_grains
            or any(len(set(face)) != len(face) for face in faces.tolist())):
        raise MesostructureError(f"mesostructure {name!r}: {cell.boundary_rule} in 1..{n_grains}")
    undriven = [int(g) + 1 for g in np.unique(outer) if not driven[g].any()]
    if undriven:
        raise MesostructureError(
            f"mesostructure {name!r}: outer grain {undriven[0]} has no driven DOF; outer grains follow the cell strain")
    for axis in range(dim):
        if not driven[:, axis].any():
            raise MesostructureError(f"mesostructure {name!r}: needs at least one DOF driven along {cell.frame[axis]}")
    _check_boundary(name, position, outer)
    if not cell_measure(position, outer) > 0.0:
        raise MesostructureError(f"mesostructure {name!r}: the outer {cell.empty_boundary}")
    outside = [g + 1 for g in sorted(set(range(n_grains)) - set(np.unique(outer).tolist()))
               if not inside_outer(position, outer, position[g])]
    if outside:
        raise MesostructureError(f"mesostructure {name!r}: grain {outside[0]} lies outside the cell's outer "
                                 f"{cell.boundary}")
    listed = set(map(tuple, pairs.tolist()))
    for i, j in combinations(range(n_grains), 2):
        gap = math.dist(position[i], position[j]) - radius[i] - radius[j]
        if gap < -tolerance * (radius[i] + radius[j]):
            raise MesostructureError(
                f"mesostructure {name!r}: grains {i + 1} and {j + 1} overlap by {-gap:.3g} m "
                f"(more than the contact tolerance)")
        if gap <= tolerance * (radius[i] + radius[j]) and (i, j) not in listed:
            raise MesostructureError(f"mesostructure {name!r}: grains {i + 1} and {j + 1} touch but are not a "
                                     f"candidate pair (their contact would carry no force): add [{i + 1}, {j + 1}] "
                                     f"to pairs")


def _check_boundary(name: str, position: np.ndarray, outer: np.ndarray) -> None:
    """MesostructureError (one line) where the outer boundary does not enclose a region once: a planar polygon whose
    edges cross or touch other than at shared corners, or triangles that do not close an oriented surface (each edge
    a -> b of one triangle once, and b -> a of another once), whose area or volume would be wrong."""
    if outer.ndim == 1:
        p = position[outer]
        n = p.shape[0]
        for i, j in combinations(range(n), 2):
            if j - i in (1, n - 1):
                continue  # adjacent edges share a corner
            if _segments_meet(p[i], p[(i + 1) % n], p[j], p[(j + 1) % n]):
                raise MesostructureError(f"mesostructure {name!r}: the outer polygon's edges {outer[i] + 1}-"
                                         f"{outer[(i + 1) % n] + 1} and {outer[j] + 1}-{outer[(j + 1) % n] + 1} "
                                         f"cross: its grains must go round the cell in order")
        return
    edges = [(int(f[k]), int(f[(k + 1) % 3])) for f in outer.tolist() for k in range(3)]
    seen = set(edges)
    bad = next((e for e in edges if edges.count(e) > 1 or (e[1], e[0]) not in seen), None)
    if bad is not None:
        raise MesostructureError(f"mesostructure {name!r}: the outer triangles do not close an oriented surface at "
                                 f"edge {bad[0] + 1}-{bad[1] + 1} (each edge must be walked once each way, by two "
                                 f"triangles of one orientation)")


def _segments_meet(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> bool:
    """Whether the planar segments a-b and c-d cross or touch."""
    def side(p, q, r):
        return float(np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])))

    def within(p, q, r):  # r on the line through p, q: inside their box
        return min(p[0], q[0]) <= r[0] <= max(p[0], q[0]) and min(p[1], q[1]) <= r[1] <= max(p[1], q[1])

    s1, s2, s3, s4 = side(a, b, c), side(a, b, d), side(c, d, a), side(c, d, b)
    if s1 * s2 < 0 and s3 * s4 < 0:
        return True
    return any(s == 0 and within(p, q, r) for s, p, q, r in ((s1, a, b, c), (s2, a, b, d), (s3, c, d, a), (s4, c, d, b)))


def inside_outer(position: np.ndarray, outer: np.ndarray, point: np.ndarray) -> bool:
    """Whether ``point`` [m] lies inside the closed outer boundary through ``position`` [m] (n_grains, dim): the winding
    number of the polygon ``outer`` (n_outer,) (2D) or the solid angle of the triangles ``outer`` (n_faces, 3) (3D, Van
    Oosterom and Strackee) about it, nonzero inside; convex or not."""
    if outer.ndim == 1:
        rel = position[outer] - point
        angle = np.arctan2(rel[:, 1], rel[:, 0])
        turn = np.diff(np.append(angle, angle[0]))
        return abs(float(np.sum((turn + np.pi) % (2.0 * np.pi) - np.pi))) > np.pi
    r = position[outer] - point  # (faces, 3 corners, 3)
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
    numerator = np.einsum("fi,fi->f", a, np.cross(b, c))
    denominator = (la * lb * lc + np.einsum("fi,fi->f", a, b) * lc + np.einsum("fi,fi->f", a, c) * lb
                   + np.einsum("fi,fi->f", b, c) * la)
    return abs(float(np.sum(2.0 * np.arctan2(numerator, denominator)))) > 2.0 * np.pi


def shares_state_schema(meso: Mesostructure, other: Mesostructure, rtol: float = 1e-12) -> bool:
    """True when every cell of ``other`` is a state of ``meso``'s learning state.

    Same radii, pairs, driven mask and outer polygon, and the same driven coordinates
    relative to the cell size (x_ref / l_ref, to ``rtol``), so that x = x_ref * l / l_ref
    places the driven DOFs identically. The H-cells of all opening angles share one schema.
    """
    same = (np.array_equal(meso.radius, other.radius) and np.array_equal(meso.pairs, other.pairs)
            and np.array_equal(meso.driven, other.driven) and np.array_equal(meso.outer, other.outer))
    if not same:
        return False
    mine = (meso.position / meso.cell_size)[meso.driven]
    theirs = (other.position / other.cell_size)[other.driven]
    return bool(np.allclose(mine, theirs, rtol=rtol, atol=rtol))


def per_cell(mesostructure: Mesostructure | Sequence[Mesostructure],
             n_cells: int) -> tuple[tuple[Mesostructure, ...], np.ndarray]:
    """The distinct mesostructures of a batch and the index of each cell's one.

    Args:
        mesostructure: one mesostructure for every cell, or a sequence of ``n_cells``, one
            per cell (cells that share a ``Mesostructure`` object share its entry).
        n_cells: number of cells, >= 1.

    Returns:
        distinct: the mesostructures in order of first use (compared by identity);
        index: int64, shape (n_cells,), cell i starts from ``distinct[index[i]]``.

    Raises:
        ValueError: fewer than one cell, or a sequence whose length is not ``n_cells``.
    """
    n_cells = int(n_cells)
    if n_cells < 1:
        raise ValueError(f"n_cells = {n_cells} must be >= 1")
    if isinstance(mesostructure, Mesostructure):
        return (mesostructure,), np.zeros(n_cells, dtype=np.int64)
    cells = list(mesostructure)
    if len(cells) != n_cells:
        raise ValueError(f"need one mesostructure or n_cells = {n_cells} of them, got {len(cells)}")
    slot: dict[int, int] = {}
    distinct: list[Mesostructure] = []
    index = np.empty(n_cells, dtype=np.int64)
    for i, meso in enumerate(cells):
        if not isinstance(meso, Mesostructure):
            raise ValueError(f"cell {i}: {type(meso).__name__} is not a Mesostructure")
        k = slot.setdefault(id(meso), len(distinct))
        if k == len(distinct):
            distinct.append(meso)
        index[i] = k
    return tuple(distinct), index


TOPOLOGY_FIELDS = {"pairs": "pairs", "driven": "driven", "outer": "outer", LABEL_KEY: "pair_label"}
"""Array name -> Mesostructure field of the arrays that describe a batch's topology (``topology_arrays``)."""
TOPOLOGY_ARRAYS = tuple(TOPOLOGY_FIELDS)
"""Names of the topology arrays."""


def topology_arrays(meso: Mesostructure, n_cells: int) -> dict[str, np.ndarray]:
    """The topology of ``meso`` repeated for ``n_cells`` cells: array name -> ``(n_cells, *field shape)``."""
    return {name: np.repeat(getattr(meso, field)[None], n_cells, axis=0) for name, field in TOPOLOGY_FIELDS.items()}


def evaluate_observables(meso: Mesostructure, position: np.ndarray, normal_force: np.ndarray, shear_force: np.ndarray,
                         contact: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The observables ``meso`` declares, evaluated on a batch of its cells (``OBSERVABLE_KINDS``).

    Args:
        position: grain centres [m], shape (n, n_grains, 2).
        normal_force: normal force of every pair [N], shape (n, n_pairs), compression positive.
        shear_force: tangential spring force of every pair [N], shape (n, n_pairs), the DEM's
            convention (on the pair's first grain along w = (-u_t, u_n)).
        contact: contact flags (n, n_pairs); None leaves the ``contact`` observables out.

    Returns:
        name -> values, shape (n,) each (bool for contact flags).
    """
    out: dict[str, np.ndarray] = {}
    for o in meso.observables:
        a, b = o.grains
        if o.kind in ("branch_angle", "branch_length"):
            branch = position[:, b] - position[:, a]
            out[o.name] = (np.degrees(libm.atan2(branch[:, 1], branch[:, 0])) if o.kind == "branch_angle"
                           else np.hypot(branch[:, 0], branch[:, 1]))
        elif o.kind == "contact":
            if contact is not None:
                out[o.name] = np.asarray(contact)[:, meso.pair_index(a, b)] == 1
        else:
            values = normal_force if o.kind == "normal_force" else shear_force
            out[o.name] = np.array(np.asarray(values)[:, meso.pair_index(a, b)])
    return out


def _pair_label(pair: np.ndarray) -> str:
    return f"{int(pair[0]) + 1}_{int(pair[1]) + 1}"


def state_schema(meso: Mesostructure) -> StateSchema:
    """The learning state of ``meso`` (see ``warp_hcell.core.contract.StateSchema``).

    Features (storage order): ``cell_size`` (l1, l2) [m] driven; ``free_position``
    (``x_n3``, ``x_t7``, ...) [m] learned; ``shear_force`` (``fs_1_2``, ...) [N] history;
    ``contact`` (``contact_1_2``, ...) derived; ``normal_force`` (``fn_1_2``, ...) [N] derived,
    >= 0; ``unbalanced`` (``f_n3``, ...) [N] net force on each free DOF, derived;
    ``moment`` (S_nn, S_nt, S_tn, S_tt) [N m] Love-Weber sum, compression positive, derived;
    ``area`` [m^2] derived. A spatial cell has (l1, l2, l3), axes n, t1, t2 in the DOF names,
    a spring force vector per pair (``fs_1_2`` of shape (3,): components n, t1, t2), the nine
    components of the moment (row-major, S_nn, S_nt1, ...) and the volume [m^3] as ``area``.
    """
    cell = dimension(meso.dim)
    axes = cell.frame
    free_dofs = np.argwhere(~meso.driven).astype(np.int64)
    dof_names = tuple(f"{axes[axis]}{grain + 1}" for grain, axis in free_dofs)
    pair_names = tuple(_pair_label(p) for p in meso.pairs)
    sizes = tuple(f"l{k + 1}" for k in range(meso.dim))
    frame = ", ".join(axes)
    features = {
        "cell_size": StateFeature(sizes, "m", "driven", f"cell size ({', '.join(sizes)}); l <- l (1 - d_eps)"),
        "free_position": StateFeature(tuple("x_" + n for n in dof_names), "m", "learned",
                                      f"coordinates of the free DOFs in the local frame ({frame})"),
        "shear_force": StateFeature(tuple("fs_" + n for n in pair_names), "N", "history", cell.spring),
        "contact": StateFeature(tuple("contact_" + n for n in pair_names), "bool", "derived",
                                "1 where gap <= contact_tolerance (r_i + r_j)"),
        "normal_force": StateFeature(tuple("fn_" + n for n in pair_names), "N", "derived",
                                     "normal contact force kn max(r_i + r_j - |x_j - x_i|, 0) of pairs in contact, >= 0"),
        "unbalanced": StateFeature(tuple("f_" + n for n in dof_names), "N", "derived",
                                   "net contact force on each free DOF (~0 at equilibrium)"),
        "moment": StateFeature(tuple(f"S_{a}{b}" for a in axes for b in axes), "N m", "derived",
                               "Love-Weber sum over the contacts, compression positive"),
        "area": StateFeature(("area",), f"m^{meso.dim}", "derived", f"{cell.measure} V_cell of the outer {cell.boundary}"),
    }
    return StateSchema(free_dofs=free_dofs, pairs=np.array(meso.pairs), radius=np.array(meso.radius),
                       reference_position=np.array(meso.position), reference_cell_size=np.array(meso.cell_size),
                       driven=np.array(meso.driven), outer=np.array(meso.outer), features=features)
