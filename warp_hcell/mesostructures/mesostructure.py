"""Few-grain mesostructures of one cell: disks, driven DOFs, candidate contacts, outer polygon.

A ``Mesostructure`` is a frozen numpy description of ONE cell in its local frame
(index 0 = n, the cell axis; index 1 = t, the lateral direction). Every degree of freedom
(grain, direction) is either driven or free. A driven coordinate follows the cell strain
homothetically: x_n = x_n,ref * l1 / l1_ref and x_t = x_t,ref * l2 / l2_ref. Free
coordinates are integrated by the DEM. The outer polygon (ordered grains) has area V_cell.

Exports:

- ``Mesostructure``: the description (validated on construction).
- ``MesostructureError``: raised, with a one-line message, for invalid descriptions.
- ``h_cell(alpha0_deg, radius)``: the six-grain H-cell of spec section 2 (the only code
  that knows the H-cell has six grains).
- ``h_cell_reference(alpha0_deg, radius)``: vectorised H-cell reference positions and cell
  sizes for a batch of alpha0.
- ``load_mesostructure(path)``: read a TOML or JSON description (format in its docstring;
  examples in ``warp_hcell/data``).
- ``state_schema(meso)``: the learning state of the cell (``warp_hcell.core.contract.StateSchema``).
- ``describe(meso)`` / ``from_description(text)`` / ``description_sha256(text)``: canonical
  JSON text of a mesostructure (stored in databases and checkpoints), its inverse, and
  its hash.
- ``shares_state_schema(a, b)``: True when cells of ``b`` are states of ``a``'s schema.
- ``per_cell(mesostructure, n_cells)``: the distinct mesostructures of a batch of cells and
  each cell's index into them (``CellModel.init_state`` takes one or one per cell).
- ``topology_arrays(meso, n_cells)``: the topology repeated per cell, for state arrays
  that must rebuild their cells (``warp_hcell.dem.cell.DemCell.state_from_arrays``).
"""

from __future__ import annotations

import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from warp_hcell.core.contract import StateFeature, StateSchema
from warp_hcell.core.parameters import CellDefaults, check_alpha0_deg, check_positive, DemSettings

H_TYPE1_PAIRS = ((1, 2), (1, 6), (3, 4), (4, 5))
"""Type-1 contacts of the H-cell as (label, label), labels 1..6 of spec section 2."""
H_TYPE2_PAIRS = ((2, 3), (5, 6))
"""Type-2 contacts of the H-cell (parallel to n)."""


AXIS_NAMES = {2: ("n", "t"), 3: ("n", "t1", "t2")}
"""Names of the local axes of a planar and of a spatial cell."""


class MesostructureError(ValueError):
    """An invalid mesostructure description; the message is one line."""


@dataclass(frozen=True, eq=False)
class Mesostructure:
    """One cell made of a few disks, in the local frame (index 0 = n, index 1 = t).

    A cell is planar (dim = 2, disks, frame (n, t)) or spatial (dim = 3, spheres, frame
    (n, t1, t2)); the dimension is the number of position columns.

    Attributes:
        name: short description.
        radius: grain radii [m], shape (n_grains,), > 0. Grain label = index + 1.
        position: reference centre positions [m], shape (n_grains, dim), (x_n, x_t) or
            (x_n, x_t1, x_t2).
        driven: True where the DOF (grain, direction) is driven by the cell strain,
            shape (n_grains, dim) bool; False = free (integrated by the DEM).
        pairs: candidate contact pairs (i, j), i < j, 0-based, shape (n_pairs, 2).
        outer: the outer boundary whose measure is V_cell: in 2D the ordered 0-based grain
            indices of a polygon, shape (n_outer,); in 3D the triangles of a closed surface
            through grain centres, oriented outwards, shape (n_faces, 3).
        cell_size: reference cell size (l1_ref, l2_ref[, l3_ref]) [m], shape (dim,).
        pair_type: H-cell label of each pair, shape (n_pairs,): 1 = type-1, 2 = type-2,
            0 = unlabelled. All zeros for a mesostructure without H-cell labels.
    """

    name: str
    radius: np.ndarray
    position: np.ndarray
    driven: np.ndarray
    pairs: np.ndarray
    outer: np.ndarray
    cell_size: np.ndarray
    pair_type: np.ndarray = field(default=None)  # type: ignore[assignment]
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
        pair_type = (np.zeros(pairs.shape[0], np.int8) if self.pair_type is None
                     else np.asarray(self.pair_type, dtype=np.int8).reshape(-1))
        _validate(self.name, radius, position, driven, pairs, outer, cell_size, pair_type,
                  self.contact_tolerance)
        for name, value in (("radius", radius), ("position", position), ("driven", driven.astype(bool)),
                            ("pairs", pairs), ("outer", outer), ("cell_size", cell_size),
                            ("pair_type", pair_type)):
            value = np.array(value)
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def n_grains(self) -> int:
        """Number of grains."""
        return int(self.radius.size)

    @property
    def dim(self) -> int:
        """Spatial dimension: 2 (disks) or 3 (spheres)."""
        return int(self.position.shape[1])

    @property
    def n_pairs(self) -> int:
        """Number of candidate contact pairs."""
        return int(self.pairs.shape[0])

    @property
    def is_h_cell(self) -> bool:
        """True when the H-cell labels (type-1 contact 1-2, type-2 contact 2-3) are attached."""
        return self.h_reference_pairs is not None

    @property
    def h_reference_pairs(self) -> tuple[int, int] | None:
        """Pair indices of the reference contacts 1-2 (type 1) and 2-3 (type 2), or None."""
        found = []
        for (i, j), kind in (((0, 1), 1), ((1, 2), 2)):
            hit = np.flatnonzero((self.pairs[:, 0] == i) & (self.pairs[:, 1] == j) & (self.pair_type == kind))
            if hit.size != 1:
                return None
            found.append(int(hit[0]))
        return found[0], found[1]

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


def polyhedron_volume(position: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Volume [m^3] enclosed by the triangles ``faces`` (n_faces, 3) through ``position`` (..., n_grains, 3).

    |sum over faces of x_a . (x_b x x_c)| / 6 (divergence theorem; the faces must close the surface).
    """
    face = np.asarray(faces)
    a, b, c = position[..., face[:, 0], :], position[..., face[:, 1], :], position[..., face[:, 2], :]
    return np.abs(np.einsum("...fi,...fi->...", a, np.cross(b, c))) / 6.0


def cell_measure(position: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """V_cell of cells: polygon area in 2D (``outer`` (n_outer,)), polyhedron volume in 3D (``outer`` (n_faces, 3))."""
    return polyhedron_volume(position, outer) if np.ndim(outer) == 2 else polygon_area(position, outer)


def _validate(name, radius, position, driven, pairs, outer, cell_size, pair_type, tolerance) -> None:
    n_grains = radius.size
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
    if pair_type.shape != (pairs.shape[0],) or not np.all(np.isin(pair_type, (0, 1, 2))):
        raise MesostructureError(f"mesostructure {name!r}: pair types must be 0, 1 or 2, one per pair")
    if dim == 2:
        if outer.size < 3 or len(set(outer.tolist())) != outer.size or outer.min() < 0 or outer.max() >= n_grains:
            raise MesostructureError(f"mesostructure {name!r}: outer polygon needs >= 3 distinct grains in 1..{n_grains}")
    elif (outer.shape[0] < 4 or outer.min() < 0 or outer.max() >= n_grains
          or any(len(set(face)) != 3 for face in outer.tolist())):
        raise MesostructureError(f"mesostructure {name!r}: outer surface needs >= 4 triangles of distinct grains in "
                                 f"1..{n_grains}")
    undriven = [int(g) + 1 for g in np.unique(outer) if not driven[g].any()]
    if undriven:
        raise MesostructureError(
            f"mesostructure {name!r}: outer grain {undriven[0]} has no driven DOF; outer grains follow the cell strain")
    axes = AXIS_NAMES[dim]
    for axis in range(dim):
        if not driven[:, axis].any():
            raise MesostructureError(f"mesostructure {name!r}: needs at least one DOF driven along {axes[axis]}")
    if not cell_measure(position, outer) > 0.0:
        raise MesostructureError(f"mesostructure {name!r}: the outer {'polygon has zero area' if dim == 2 else 'surface encloses no volume'}")
    for i, j in combinations(range(n_grains), 2):
        gap = math.dist(position[i], position[j]) - radius[i] - radius[j]
        if gap < -tolerance * (radius[i] + radius[j]):
            raise MesostructureError(
                f"mesostructure {name!r}: grains {i + 1} and {j + 1} overlap by {-gap:.3g} m "
                f"(more than the contact tolerance)")


def h_cell_reference(alpha0_deg: float | np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Touching H-cell reference positions and cell sizes for a batch of opening angles.

    Args:
        alpha0_deg: initial opening angles [deg], scalar or shape (n_cells,), each in [30, 90).
        radius: grain radius r [m] (all six grains equal, D = 2 r).

    Returns:
        position: (n_cells, 6, 2) [m], (x_n, x_t) of grains 1..6 with d1 = d2 = D;
        cell_size: (n_cells, 2) [m], (l1, l2) = (D + 2 D cos a, 2 D sin a).
    """
    alpha0_deg = np.atleast_1d(np.asarray(alpha0_deg, dtype=np.float64))
    for value in np.unique(alpha0_deg):
        check_alpha0_deg(value)
    diameter = 2.0 * check_positive("radius", radius)
    alpha = np.radians(alpha0_deg)
    top = diameter / 2.0 + diameter * np.cos(alpha)
    side = diameter * np.sin(alpha)
    half = np.full_like(alpha, diameter / 2.0)
    zero = np.zeros_like(alpha)
    x_n = np.stack([top, half, -half, -top, -half, half], axis=1)
    x_t = np.stack([zero, -side, -side, zero, side, side], axis=1)
    cell_size = np.stack([2.0 * top, 2.0 * side], axis=1)
    return np.stack([x_n, x_t], axis=2), cell_size


def h_cell(alpha0_deg: float = CellDefaults.alpha0_deg, radius: float = CellDefaults.radius) -> Mesostructure:
    """The six-grain H-cell of spec section 2, touching and force-free.

    Grains 1 and 4 are driven along n and t (x_t = 0); grains 2, 3, 5, 6 are driven along t
    and free along n. All 15 pairs are candidates; type-1 and type-2 contacts are labelled.
    The outer polygon is the hexagon 1-2-3-4-5-6.

    Args:
        alpha0_deg: initial opening angle [deg], in [30, 90).
        radius: grain radius r [m].
    """
    position, cell_size = h_cell_reference(alpha0_deg, radius)
    driven = np.array([[True, True]] + [[False, True]] * 2 + [[True, True]] + [[False, True]] * 2)
    return _with_labels(
        name=f"h-cell alpha0={float(alpha0_deg):g} deg",
        radius=np.full(6, float(radius)), position=position[0], driven=driven,
        outer=np.arange(6), cell_size=cell_size[0],
        type1=H_TYPE1_PAIRS, type2=H_TYPE2_PAIRS)


def _with_labels(*, name, radius, position, driven, outer, cell_size, type1, type2, pairs=None,
                 contact_tolerance=DemSettings.contact_tolerance) -> Mesostructure:
    """Build a Mesostructure with all pairs (unless given) and type-1/type-2 labels (1-based)."""
    n_grains = len(radius)
    pairs = list(combinations(range(n_grains), 2)) if pairs is None else [tuple(sorted(p)) for p in pairs]
    labels = {tuple(sorted((a - 1, b - 1))): 1 for a, b in type1}
    labels.update({tuple(sorted((a - 1, b - 1))): 2 for a, b in type2})
    unknown = set(labels) - set(pairs)
    if unknown:
        a, b = sorted(unknown)[0]
        raise MesostructureError(f"mesostructure {name!r}: labelled pair {a + 1}-{b + 1} is not a candidate pair")
    pair_type = [labels.get(p, 0) for p in pairs]
    return Mesostructure(name=name, radius=np.asarray(radius, float), position=np.asarray(position, float),
                         driven=np.asarray(driven), pairs=np.asarray(pairs, dtype=np.int64).reshape(-1, 2),
                         outer=np.asarray(outer), cell_size=np.asarray(cell_size, float),
                         pair_type=np.asarray(pair_type), contact_tolerance=contact_tolerance)


def load_mesostructure(path: str | Path, *, contact_tolerance: float = DemSettings.contact_tolerance) -> Mesostructure:
    """Read a mesostructure from a TOML (``.toml``) or JSON (``.json``) file.

    Format (labels are 1-based, coordinates (n, t) in metres)::

        name = "h-cell, lateral grains 0.7 D"
        cell_size = [l1_ref, l2_ref]
        outer = [1, 2, 3, 4, 5, 6]          # ordered around the polygon whose area is V_cell
        pairs = [[1, 2], ...]               # optional; default: all pairs
        type1 = [[1, 2], [1, 6], ...]       # optional H-cell labels (enable N1, N2, T1, alpha)
        type2 = [[2, 3], [5, 6]]
        [[grains]]                          # one table per grain, in label order
        radius = 0.5
        position = [x_n, x_t]
        driven = [true, false]              # (along n, along t)

    A 3D cell (spheres) gives three coordinates per grain, position = [x_n, x_t1, x_t2] and
    driven = [n, t1, t2], a cell_size of three lengths, and ``outer`` as the triangles of the
    closed surface whose volume is V_cell, oriented outwards: outer = [[1, 6, 10], ...].

    Raises:
        MesostructureError: unreadable file or invalid description (one-line message).
    """
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError) as exc:
        raise MesostructureError(f"cannot read mesostructure file {path}: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise MesostructureError(f"mesostructure file {path} is not valid {path.suffix[1:].upper()}: {exc}") from None
    return _from_mapping(data, default_name=path.stem, contact_tolerance=contact_tolerance)


def _from_mapping(data: Mapping[str, Any], *, default_name: str, contact_tolerance: float) -> Mesostructure:
    name = str(data.get("name", default_name))
    try:
        grains = data["grains"]
        radius = [float(g["radius"]) for g in grains]
        position = [[float(v) for v in g["position"]] for g in grains]
        driven = [list(g["driven"]) for g in grains]
        dim = len(position[0]) if position else 2
        if not all(isinstance(v, bool) and len(d) == dim for d in driven for v in d):
            axes = AXIS_NAMES.get(dim, AXIS_NAMES[2])
            raise MesostructureError(f"mesostructure {name!r}: each grain needs driven = [{', '.join(['bool'] * len(axes))}] "
                                     f"({', '.join(axes)})")
        to_index = lambda labels: [[int(a) - 1 for a in p] for p in labels]  # noqa: E731
        pairs = data.get("pairs")
        return _with_labels(
            name=name, radius=radius, position=position, driven=driven,
            outer=np.asarray(data["outer"], dtype=np.int64) - 1, cell_size=[float(v) for v in data["cell_size"]],
            pairs=None if pairs is None else to_index(pairs),
            type1=[tuple(p) for p in data.get("type1", ())], type2=[tuple(p) for p in data.get("type2", ())],
            contact_tolerance=contact_tolerance)
    except KeyError as exc:
        raise MesostructureError(f"mesostructure {name!r}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, MesostructureError):
            raise
        raise MesostructureError(f"mesostructure {name!r}: malformed entry ({exc})") from None


DESCRIPTION_FIELDS = ("radius", "position", "driven", "pairs", "outer", "cell_size", "pair_type")
"""Array fields of a mesostructure in its JSON description (with ``name``, ``contact_tolerance``)."""


def describe(meso: Mesostructure) -> str:
    """Canonical JSON text of ``meso``: enough to rebuild it with ``from_description``.

    Canonical: keys sorted, no whitespace (``json.dumps(sort_keys=True, separators=(",", ":"))``),
    floats written by ``repr`` (exact round trip), indices 0-based. Equal cells give equal text.
    """
    data: dict[str, Any] = {"format": "meso-hmodel-mesostructure", "version": 1, "name": meso.name,
                            "contact_tolerance": float(meso.contact_tolerance)}
    for name in DESCRIPTION_FIELDS:
        data[name] = np.asarray(getattr(meso, name)).tolist()
    return json.dumps(data, sort_keys=True, separators=(",", ":"))


def from_description(text: str) -> Mesostructure:
    """Inverse of ``describe``.

    Raises:
        MesostructureError: not a mesostructure description, or an invalid cell (one line).
    """
    try:
        data = json.loads(text)
    except (TypeError, json.JSONDecodeError) as exc:
        raise MesostructureError(f"mesostructure description is not JSON: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != "meso-hmodel-mesostructure":
        raise MesostructureError("text is not a mesostructure description (format meso-hmodel-mesostructure)")
    try:
        return Mesostructure(
            name=str(data["name"]), radius=np.asarray(data["radius"], np.float64),
            position=np.asarray(data["position"], np.float64), driven=np.asarray(data["driven"], bool),
            pairs=np.asarray(data["pairs"], np.int64).reshape(-1, 2), outer=np.asarray(data["outer"], np.int64),
            cell_size=np.asarray(data["cell_size"], np.float64), pair_type=np.asarray(data["pair_type"], np.int8),
            contact_tolerance=float(data["contact_tolerance"]))
    except KeyError as exc:
        raise MesostructureError(f"mesostructure description: missing key {exc.args[0]!r}") from None


def description_sha256(text: str) -> str:
    """Hex sha256 of a description text (UTF-8)."""
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


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


TOPOLOGY_ARRAYS = ("pairs", "driven", "outer", "pair_type")
"""Mesostructure fields that describe a batch's topology (``topology_arrays``)."""


def topology_arrays(meso: Mesostructure, n_cells: int) -> dict[str, np.ndarray]:
    """``TOPOLOGY_ARRAYS`` of ``meso`` repeated for ``n_cells`` cells: field -> ``(n_cells, *field shape)``."""
    return {name: np.repeat(getattr(meso, name)[None], n_cells, axis=0) for name in TOPOLOGY_ARRAYS}


def _pair_label(pair: np.ndarray) -> str:
    return f"{int(pair[0]) + 1}_{int(pair[1]) + 1}"


def state_schema(meso: Mesostructure) -> StateSchema:
    """The learning state of ``meso`` (see ``warp_hcell.core.contract.StateSchema``).

    Features (storage order): ``cell_size`` (l1, l2) [m] driven; ``free_position``
    (``x_n3``, ``x_t7``, ...) [m] learned; ``shear_force`` (``fs_1_2``, ...) [N] history;
    ``contact`` (``contact_1_2``, ...) derived; ``normal_force`` (``fn_1_2``, ...) [N] derived,
    >= 0; ``unbalanced`` (``f_n3``, ...) [N] net force on each free DOF, derived;
    ``moment`` (S_nn, S_nt, S_tn, S_tt) [N m] Love-Weber sum, compression positive, derived;
    ``area`` [m^2] derived.
    """
    free_dofs = np.argwhere(~meso.driven).astype(np.int64)
    dof_names = tuple(f"{AXIS_NAMES[meso.dim][axis]}{grain + 1}" for grain, axis in free_dofs)
    pair_names = tuple(_pair_label(p) for p in meso.pairs)
    features = {
        "cell_size": StateFeature(("l1", "l2"), "m", "driven", "cell size (l1, l2); l <- l (1 - d_eps)"),
        "free_position": StateFeature(tuple("x_" + n for n in dof_names), "m", "learned",
                                      "coordinates of the free DOFs in the local frame (n, t)"),
        "shear_force": StateFeature(tuple("fs_" + n for n in pair_names), "N", "history",
                                    "tangential spring force of each pair, on grain i along w = (-u_t, u_n), "
                                    "u = (x_j - x_i) / |x_j - x_i|; zero out of contact"),
        "contact": StateFeature(tuple("contact_" + n for n in pair_names), "bool", "derived",
                                "1 where gap <= contact_tolerance (r_i + r_j)"),
        "normal_force": StateFeature(tuple("fn_" + n for n in pair_names), "N", "derived",
                                     "normal contact force kn max(r_i + r_j - |x_j - x_i|, 0) of pairs in contact, >= 0"),
        "unbalanced": StateFeature(tuple("f_" + n for n in dof_names), "N", "derived",
                                   "net contact force on each free DOF (~0 at equilibrium)"),
        "moment": StateFeature(("S_nn", "S_nt", "S_tn", "S_tt"), "N m", "derived",
                               "Love-Weber sum over the contacts, compression positive"),
        "area": StateFeature(("area",), "m^2", "derived", "area V_cell of the outer polygon"),
    }
    return StateSchema(free_dofs=free_dofs, pairs=np.array(meso.pairs), radius=np.array(meso.radius),
                       reference_position=np.array(meso.position), reference_cell_size=np.array(meso.cell_size),
                       driven=np.array(meso.driven), outer=np.array(meso.outer), features=features)
