"""The H-cell, the only code that knows it: geometry, builders, labels, declared observables, closed forms.

The H-cell of spec section 2 is six disks around a pore; its family adds unequal lateral
grains and free fine grains in the pore (``build_h_cell``). Grain labels 1..6 (array
index = label - 1), local frame index 0 = n (cell axis), 1 = t (lateral direction)::

          1              1 = (n:  l1/2, t: 0)
       2     6           2 = (n:  y2,   t: -l2/2)    6 = (n:  y2, t: +l2/2)
       3     5           3 = (n: -y2,   t: -l2/2)    5 = (n: -y2, t: +l2/2)
          4              4 = (n: -l1/2, t: 0)

with y2 = d2/2, l1 = d2 + 2 d1 cos(alpha) and l2 = 2 d1 sin(alpha). Angles in radians
inside, ``_deg`` in degrees.

Exports:

- ``h_cell(alpha0_deg, radius)``: the six-equal-grain H-cell, touching and force-free;
  ``build_h_cell(...)``: the family (``lateral``, ``fines``); ``reference``: vectorised
  reference positions and cell sizes; ``skeleton``; ``pore_ratio``.
- Labels: pairs 1-2, 1-6, 3-4, 4-5 are type-1 contacts, 2-3 and 5-6 type-2 (``TYPE1_PAIRS``,
  ``TYPE2_PAIRS``), stored as ``Mesostructure.pair_label`` 1 / 2. A cell with labels on
  the reference contacts 1-2 (type 1) and 2-3 (type 2) declares the observables
  ``OBSERVABLES`` (alpha_deg, d1, d2, N1, N2, T1, closed1, closed2) and the parameter
  ``alpha0_deg`` (``declare``); ``plain_alpha0(meso)`` tells whether a cell is the plain
  six-equal-grain H-cell that the closed forms model.
- Start cells of the default learning database (``StartCells``, ``start_cells``).
- Closed forms of the symmetric H-cell (spec sections 2, 3, 7), vectorised over cells
  (arrays of shape (n_cells,) or scalars that broadcast): ``lengths``,
  ``branches_from_alpha``, ``cell_area``, ``grain_positions``, ``love_weber_moment``,
  ``touching_cells``; the analytical backend models exactly this cell with them.

Sign convention: compression positive (contact forces N1, N2 > 0 push grains apart, the
Love-Weber moment of a compressed cell is positive); T1 > 0 resists opening (alpha growing).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from itertools import combinations
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from warp_hcell.core.dimension import dimension
from warp_hcell.core.parameters import (
    ALPHA_MAX_DEG,
    ALPHA_MIN_DEG,
    CellDefaults,
    DemSettings,
    check_alpha0_deg,
    check_positive,
)
from warp_hcell.mesostructures.mesostructure import inside_outer, Mesostructure, MesostructureError, PairObservable

N_GRAINS = 6
"""Grains of the H-cell skeleton (labels 1..6); fine grains follow."""
TYPE1_PAIRS = ((1, 2), (1, 6), (3, 4), (4, 5))
"""Type-1 contacts as (label, label), labels 1..6 of spec section 2; ``pair_label`` 1."""
TYPE2_PAIRS = ((2, 3), (5, 6))
"""Type-2 contacts (parallel to n); ``pair_label`` 2."""
DRIVEN = ((True, True), (False, True), (False, True), (True, True), (False, True), (False, True))
"""Driven DOFs of grains 1..6: 1 and 4 along n and t, the lateral grains along t only."""
OBSERVABLES = (
    PairObservable("alpha_deg", "branch_angle", (1, 0)),
    PairObservable("d1", "branch_length", (0, 1)),
    PairObservable("d2", "branch_length", (1, 2)),
    PairObservable("N1", "normal_force", (0, 1)),
    PairObservable("N2", "normal_force", (1, 2)),
    PairObservable("T1", "shear_force", (0, 1)),
    PairObservable("closed1", "contact", (0, 1)),
    PairObservable("closed2", "contact", (1, 2)),
)
"""What a labelled cell declares, at the reference contacts 1-2 (type 1) and 2-3 (type 2), equal
to the other type-1 / type-2 contacts by symmetry: the opening angle alpha (from n to the
branch 2 -> 1) [deg], the branch lengths d1, d2 [m], the normal forces N1, N2 [N]
(compression positive), the tangential force T1 [N] (> 0 resists opening) and the contact flags."""


def _labels(name: str, pairs: Sequence[tuple[int, int]], type1, type2) -> np.ndarray:
    """``pair_label`` of ``pairs`` (0-based) from type-1 / type-2 pairs given by 1-based labels."""
    labels = {tuple(sorted((int(a) - 1, int(b) - 1))): 1 for a, b in type1}
    both = sorted(set(labels) & {tuple(sorted((int(a) - 1, int(b) - 1))) for a, b in type2})
    if both:
        raise MesostructureError(f"mesostructure {name!r}: pair {both[0][0] + 1}-{both[0][1] + 1} is labelled both "
                                 f"type 1 and type 2")
    labels.update({tuple(sorted((int(a) - 1, int(b) - 1))): 2 for a, b in type2})
    unknown = set(labels) - {tuple(p) for p in pairs}
    if unknown:
        a, b = sorted(unknown)[0]
        raise MesostructureError(f"mesostructure {name!r}: labelled pair {a + 1}-{b + 1} is not a candidate pair")
    return np.array([labels.get(tuple(p), 0) for p in pairs], dtype=np.int8)


FILE_LABEL_KEYS = ("type1", "type2")
"""Keys of a mesostructure file that hold the H-cell's labels (lists of 1-based label pairs)."""


def file_labels(name: str, pairs: Sequence[tuple[int, int]], data: Mapping[str, Any]) -> np.ndarray:
    """``pair_label`` of a mesostructure file's pairs (0-based) from its optional ``type1`` and
    ``type2`` lists of 1-based label pairs (``FILE_LABEL_KEYS``;
    ``warp_hcell.mesostructures.files.load_mesostructure``)."""
    type1, type2 = ([tuple(p) for p in data.get(key, ())] for key in FILE_LABEL_KEYS)
    return _labels(name, pairs, type1, type2)


def _reference_labelled(meso: Mesostructure) -> bool:
    """True when the reference contacts 1-2 and 2-3 carry the type-1 and type-2 labels."""
    try:
        return (meso.pair_label[meso.pair_index(0, 1)] == 1) and (meso.pair_label[meso.pair_index(1, 2)] == 2)
    except ValueError:
        return False


def declare(meso: Mesostructure) -> Mesostructure:
    """``meso`` with the parameter ``alpha0_deg`` where its reference contacts are labelled, and
    in 2D ``OBSERVABLES``; else unchanged.

    ``alpha0_deg`` is the angle between the axis n and the branch 2 -> 1 in the reference
    geometry (a 3D cell: in plane A, (n, t1)), rounded to 1e-9 deg (the cell built at
    ``alpha0`` gives back exactly ``alpha0`` for any value with at most nine decimals).
    """
    if meso.dim not in (2, 3) or not _reference_labelled(meso):
        return meso
    branch = meso.position[0] - meso.position[1]
    lateral = branch[1] if meso.dim == 2 else math.hypot(*branch[1:])
    alpha0 = round(math.degrees(math.atan2(lateral, branch[0])), 9)
    observables = OBSERVABLES if meso.dim == 2 else meso.observables
    return replace(meso, observables=observables, parameters={**meso.parameters, "alpha0_deg": alpha0})


def reference(alpha0_deg: float | np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
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
    position, cell_size = reference(alpha0_deg, radius)
    name = f"h-cell alpha0={float(alpha0_deg):g} deg"
    pairs = list(combinations(range(N_GRAINS), 2))
    return declare(Mesostructure(name=name, radius=np.full(N_GRAINS, float(radius)), position=position[0],
                                 driven=np.array(DRIVEN), pairs=np.array(pairs, dtype=np.int64),
                                 outer=np.arange(N_GRAINS), cell_size=cell_size[0],
                                 pair_label=_labels(name, pairs, TYPE1_PAIRS, TYPE2_PAIRS)))


def skeleton(alpha0_deg: float, radius: float, lateral: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Touching H-cell whose lateral grains have radius ``lateral * radius``.

    Args:
        alpha0_deg: opening angle [deg], in [30, 90).
        radius: radius r of grains 1 and 4 [m].
        lateral: radius of grains 2, 3, 5, 6 over r [-], > 0.

    Returns:
        radius (6,) [m], position (6, 2) [m] as (x_n, x_t) with the pore centre at the
        origin, cell_size (l1, l2) [m] = (d2 + 2 d1 cos a, 2 d1 sin a).
    """
    alpha = math.radians(check_alpha0_deg(alpha0_deg))
    r_lat = lateral * radius
    if lateral == 1.0:  # the same floating-point values as h_cell
        position, cell_size = reference(alpha0_deg, radius)
        return np.full(N_GRAINS, float(radius)), position[0], cell_size[0]
    d1, d2 = radius + r_lat, 2.0 * r_lat
    top, side = d2 / 2.0 + d1 * math.cos(alpha), d1 * math.sin(alpha)
    position = np.array([[top, 0.0], [d2 / 2, -side], [-d2 / 2, -side],
                         [-top, 0.0], [-d2 / 2, side], [d2 / 2, side]])
    radii = np.array([radius, r_lat, r_lat, radius, r_lat, r_lat])
    return radii, position, np.array([2.0 * top, 2.0 * side])


def pore_ratio(alpha0_deg: float, *, lateral: float = 1.0, n: float = 0.0, t: float = 0.0) -> float:
    """Largest fine-grain radius over r that fits at offset (n, t) r from the pore centre [-].

    It is the inscribed radius of the pore at that point: min over grains 1..6 of
    (distance to the grain centre - its radius), over r. At the pore centre of the equal-grain
    H-cell: sqrt(1/4 + sin^2 a) 2 - 1 (0.830 at alpha0 = 50 deg, 0.920 at 55 deg).
    """
    radii, position, _ = skeleton(alpha0_deg, 1.0, lateral)
    gap = np.hypot(position[:, 0] - n, position[:, 1] - t) - radii
    return float(gap.min())


def build_h_cell(alpha0_deg: float = CellDefaults.alpha0_deg, *, radius: float = CellDefaults.radius,
                 lateral: float = 1.0, fines: tuple[float, ...] = (),
                 fine_offsets: tuple[tuple[float, float], ...] | None = None, name: str | None = None) -> Mesostructure:
    """H-cell with lateral grains ``lateral * radius`` and free fine grains in the pore.

    Args:
        alpha0_deg: opening angle [deg], in [30, 90).
        radius: radius r of grains 1 and 4 [m], > 0.
        lateral: radius of grains 2, 3, 5, 6 over r [-], > 0.
        fines: radius of each fine grain over r [-], >= 0; zeros are left out.
        fine_offsets: (n, t) offset of each fine grain from the pore centre over r [-], one per
            entry of ``fines`` (default: the pore centre).
        name: mesostructure name (default: describes the parameters).

    Returns:
        Grains 1..6 as in spec section 2 (1, 4 driven along n and t; 2, 3, 5, 6 driven along t,
        free along n), then the fine grains (free); every pair a candidate; type-1/type-2 labels;
        outer polygon = hexagon.

    Raises:
        MesostructureError: bad parameter, a fine grain outside the pore, or overlapping grains."""
    label = name or _default_name(alpha0_deg, lateral, fines)
    for key, value in (("radius", radius), ("lateral", lateral)):
        if not (math.isfinite(value) and value > 0.0):
            raise MesostructureError(f"mesostructure {label!r}: {key} = {value:g} must be finite and > 0")
    try:
        radii, position, cell_size = skeleton(alpha0_deg, radius, lateral)
    except ValueError as exc:
        raise MesostructureError(f"mesostructure {label!r}: {exc}") from None
    offsets = [(0.0, 0.0)] * len(fines) if fine_offsets is None else list(fine_offsets)
    if len(offsets) != len(fines):
        raise MesostructureError(f"mesostructure {label!r}: {len(fines)} fine grains but {len(offsets)} positions")
    fine_radius, fine_position = _place_fines(
        label, fines, offsets, radius, 2, inside=lambda centre: inside_outer(position, np.arange(N_GRAINS), centre),
        room=lambda offset: pore_ratio(alpha0_deg, lateral=lateral, n=offset[0], t=offset[1]),
        where=lambda offset: f"n={offset[0]:g}, t={offset[1]:g}", pore="the pore (hexagon 1-2-3-4-5-6)",
        note=f" (alpha0 = {alpha0_deg:g} deg)")
    n_fines = fine_radius.size
    all_radius = np.concatenate([radii, fine_radius])
    all_position = np.concatenate([position, fine_position])
    driven = np.array([[True, True]] + [[False, True]] * 2 + [[True, True]] + [[False, True]] * 2
                      + [[False, False]] * n_fines)
    pairs = list(combinations(range(N_GRAINS + n_fines), 2))
    return declare(Mesostructure(name=label, radius=all_radius, position=all_position, driven=driven,
                                 pairs=np.array(pairs, dtype=np.int64), outer=np.arange(N_GRAINS), cell_size=cell_size,
                                 pair_label=_labels(label, pairs, TYPE1_PAIRS, TYPE2_PAIRS)))


def _place_fines(label: str, fines: Sequence[float], offsets: Sequence[Sequence[float]], radius: float,
                 position_dim: int, *,
                 inside: Callable[[np.ndarray], bool], room: Callable[[Sequence[float]], float],
                 where: Callable[[Sequence[float]], str], pore: str, note: str) -> tuple[np.ndarray, np.ndarray]:
    """Radii [m], shape (n_fines,), and centres [m], shape (n_fines, dim), of the fine grains of
    an H-cell's pore (zero ratios left out).

    Args:
        label: the mesostructure's name, for the messages.
        fines: radius of each fine grain over r [-].
        offsets: position of each from the pore centre in units of r [-], one per fine grain.
        radius: r [m].
        position_dim: the dimension of the cell (2 or 3).
        inside: whether a centre [m] lies inside the pore.
        room: the largest ratio [-] that fits at an offset.
        where: an offset as the messages write it; pore: the pore, named; note: appended to
            the message of a grain that does not fit.

    Raises:
        MesostructureError: a ratio or offset not finite, a grain outside the pore or larger
            than its room (beyond the contact tolerance; within it, it is shrunk to the room).
    """
    fine_radius, fine_position = [], []
    for k, (ratio, offset) in enumerate(zip(fines, offsets)):
        if not (math.isfinite(ratio) and ratio >= 0.0) or not all(math.isfinite(v) for v in offset):
            raise MesostructureError(f"mesostructure {label!r}: fine grain {k + 1} needs a finite ratio >= 0 "
                                     f"and a finite position, got ratio={ratio:g} at {where(offset)}")
        if ratio == 0.0:
            continue
        centre = np.asarray(offset, dtype=np.float64) * radius
        if not inside(centre):
            raise MesostructureError(f"mesostructure {label!r}: fine grain at {where(offset)} (units of r) "
                                     f"is outside {pore}")
        largest = room(offset)
        if ratio > largest * (1.0 + DemSettings.contact_tolerance):
            raise MesostructureError(f"mesostructure {label!r}: fine grain ratio {ratio:g} does not fit the pore at "
                                     f"{where(offset)}: the largest is {largest:.6g}{note}")
        fine_radius.append(min(ratio, largest) * radius)
        fine_position.append(centre)
    return np.array(fine_radius, dtype=np.float64), np.reshape(fine_position, (len(fine_radius), position_dim))


def _default_name(alpha0_deg: float, lateral: float, fines: tuple[float, ...]) -> str:
    parts = [f"h-cell alpha0={float(alpha0_deg):g} deg"]
    if lateral != 1.0:
        parts.append(f"lateral/r={lateral:g}")
    if any(f > 0.0 for f in fines):
        parts.append("fines r_f/r=" + "/".join(f"{f:g}" for f in fines))
    return ", ".join(parts)


def plain_alpha0(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0_deg, radius) if ``meso`` is the touching six-equal-grain H-cell, else None.

    The closed-form backends model exactly this cell; the comparison is to 1e-9 of the
    grain radius on positions, cell size, driven flags, pairs, labels and outer polygon.
    """
    return _plain(meso, N_GRAINS, h_cell)


def _plain(meso: Mesostructure, n_grains: int, build: Callable[[float, float], Mesostructure]
           ) -> tuple[float, float] | None:
    """(alpha0_deg, radius [m]) if ``meso`` has ``n_grains`` equal grains and is the cell that
    ``build(alpha0_deg, radius)`` builds at its declared alpha0: the same dimension, positions
    and cell size to 1e-9 of the radius, driven flags, outer polygon and labelled pairs (in any
    order); else None (also where ``build`` refuses the angle)."""
    if meso.n_grains != n_grains or not np.allclose(meso.radius, meso.radius[0], rtol=1e-12, atol=0.0):
        return None
    alpha0 = meso.parameters.get("alpha0_deg")
    if alpha0 is None:
        return None
    radius = float(meso.radius[0])
    try:
        reference = build(alpha0, radius)
    except ValueError:
        return None
    same = (meso.dim == reference.dim
            and np.allclose(meso.position, reference.position, rtol=0.0, atol=1e-9 * radius)
            and np.allclose(meso.cell_size, reference.cell_size, rtol=0.0, atol=1e-9 * radius)
            and np.array_equal(meso.driven, reference.driven) and np.array_equal(meso.outer, reference.outer)
            and {tuple(p): t for p, t in zip(meso.pairs.tolist(), meso.pair_label.tolist())}
            == {tuple(p): t for p, t in zip(reference.pairs.tolist(), reference.pair_label.tolist())})
    return (alpha0, radius) if same else None


@dataclass(frozen=True)
class StartCells:
    """Start cells of the default (H-cell) learning database: the H-cells of all opening angles
    share one learning state, so the exploration starts from several
    (``warp_hcell.database.generate``; a mesostructure file or spec gives one start cell)."""

    alpha0_min_deg: float = 30.0
    """Smallest opening angle of the start cells [deg]."""
    alpha0_max_deg: float = 89.0
    """Largest opening angle of the start cells [deg]."""
    n_alpha0: int = 12
    """Opening angles evenly spaced in [alpha0_min_deg, alpha0_max_deg] [-]."""
    alpha0_focus_deg: tuple[float, ...] = (35.0, 40.0, 55.0)
    """Opening angles of the homogenisation runs, added to the even grid [deg]."""

    def __post_init__(self) -> None:
        if int(self.n_alpha0) < 1:
            raise ValueError(f"n_alpha0 = {self.n_alpha0} must be >= 1")
        for value in (self.alpha0_min_deg, self.alpha0_max_deg, *self.alpha0_focus_deg):
            check_alpha0_deg(value)
        if self.alpha0_min_deg > self.alpha0_max_deg:
            raise ValueError(f"alpha0_min_deg = {self.alpha0_min_deg:g} exceeds alpha0_max_deg = {self.alpha0_max_deg:g}")

    def build(self, radius: float = CellDefaults.radius) -> list[Mesostructure]:
        """The H-cells at the opening angles (even grid plus focus angles), sorted."""
        grid = np.linspace(self.alpha0_min_deg, self.alpha0_max_deg, self.n_alpha0)
        angles = np.unique(np.concatenate([grid, np.asarray(self.alpha0_focus_deg, dtype=np.float64)]))
        return [h_cell(float(a), radius) for a in angles]


def lengths(d1: np.ndarray, d2: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell lengths from the branch lengths (spec section 2).

    Args:
        d1: type-1 branch length [m], shape (n_cells,).
        d2: type-2 branch length [m], shape (n_cells,).
        alpha: opening angle between the axis n and the branch 1->2 [rad], shape (n_cells,).

    Returns:
        (l1, l2) [m]: axial length centre 1 to centre 4, and distance between the lateral
        columns, each shape (n_cells,).
    """
    return d2 + 2.0 * d1 * np.cos(alpha), 2.0 * d1 * np.sin(alpha)


def branches_from_alpha(
    l1: np.ndarray, l2: np.ndarray, alpha: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Branch lengths from the cell lengths and the opening angle (spec section 11).

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        alpha: opening angle [rad], shape (n_cells,), in (0, pi/2].

    Returns:
        (d1, d2) [m]: d1 = l2 / (2 sin alpha), d2 = l1 - 2 d1 cos alpha; shape (n_cells,).
    """
    d1 = 0.5 * l2 / np.sin(alpha)
    return d1, l1 - 2.0 * d1 * np.cos(alpha)


def cell_area(l1: np.ndarray, l2: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Area of the hexagon through the six centres (spec section 2).

    V_cell = l2 (d2 + d1 cos alpha) = l2 (l1 + d2) / 2, since 2 d1 cos alpha = l1 - d2.

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        d2: type-2 branch length [m], shape (n_cells,).

    Returns:
        V_cell [m^2], shape (n_cells,).
    """
    return 0.5 * l2 * (l1 + d2)


def grain_positions(l1: np.ndarray, l2: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """Centres of the six grains in the local frame, cell centre at the origin.

    Args:
        l1, l2: cell lengths [m], shape (n_cells,).
        y2: n-coordinate of grain 2, d2/2 [m], shape (n_cells,).

    Returns:
        Positions [m], shape (n_cells, 6, 2): [:, label - 1, 0] = x_n, [:, label - 1, 1] = x_t.
    """
    return np.moveaxis(grain_rows(l1, l2, y2), (0, 1), (-2, -1))


def grain_rows(l1: np.ndarray, l2: np.ndarray, y2: np.ndarray) -> np.ndarray:
    """``grain_positions`` laid out grain, then component first: shape (6, 2, n_cells) [m], [label - 1, 0] = x_n,
    [label - 1, 1] = x_t."""
    l1, l2, y2 = np.broadcast_arrays(
        np.asarray(l1, dtype=np.float64), np.asarray(l2, dtype=np.float64), np.asarray(y2, dtype=np.float64)
    )
    hn, ht = 0.5 * l1, 0.5 * l2
    x = np.zeros((N_GRAINS, 2, *hn.shape))
    x[:, 0] = hn, y2, -y2, -hn, -y2, y2
    x[1:3, 1], x[4:6, 1] = -ht, ht
    return x


def love_weber_moment(
    alpha: np.ndarray,
    N1: np.ndarray,
    N2: np.ndarray,
    T1: np.ndarray,
    l1: np.ndarray,
    l2: np.ndarray,
    *,
    kn: float,
    diameter: float,
    normal: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Love-Weber moment S = sum_c f_c (x) l_c of the H-cell and its area (spec section 7).

    Sums the type-1 and type-2 contacts and the pathological contacts 1-4 (l1 < D) and 2-6,
    3-5 (l2 < D), which carry kn <D - l> (or ``normal(D - l)``); S_nt = 0.

    Args:
        alpha: opening angle [rad], (n_cells,), in (0, pi/2].
        N1, N2: type-1 / type-2 normal forces [N], (n_cells,), compression positive.
        T1: type-1 tangential force [N], (n_cells,), > 0 resists opening.
        l1, l2: cell lengths [m], (n_cells,).
        kn: normal stiffness of the pathological contacts [N/m]; diameter: D [m].
        normal: normal force [N] of an overlap [m] for a non-linear law; None: linear.

    Returns:
        (moment [N m], (n_cells, 2, 2), local frame (0 = n, 1 = t), compression positive;
        area V_cell [m^2], (n_cells,))."""
    c, s = np.cos(alpha), np.sin(alpha)
    axial = 0.5 * l2 * c / s  # d1 cos a = l1/2 - y2
    d2 = l1 - 2.0 * axial
    moment = np.zeros((np.shape(alpha)[0], 2, 2))
    if normal is None:
        moment[:, 0, 0] = 4.0 * axial * (N1 * c + T1 * s) + 2.0 * N2 * d2 + kn * np.maximum(diameter - l1, 0.0) * l1
        moment[:, 1, 1] = 2.0 * l2 * (N1 * s - T1 * c) + 2.0 * kn * np.maximum(diameter - l2, 0.0) * l2
    else:
        moment[:, 0, 0] = 4.0 * axial * (N1 * c + T1 * s) + 2.0 * N2 * d2 + normal(diameter - l1) * l1
        moment[:, 1, 1] = 2.0 * l2 * (N1 * s - T1 * c) + 2.0 * normal(diameter - l2) * l2
    return moment, cell_area(l1, l2, d2)


def touching_cells(alpha0_deg: float | np.ndarray, n_cells: int, diameter: float) -> tuple[np.ndarray, ...]:
    """Geometry of force-free initial cells: d1 = d2 = D at opening angle alpha0.

    Args:
        alpha0_deg: initial opening angle [deg], scalar or shape (n_cells,), each in
            [30, 90); ValueError (one line) otherwise.
        n_cells: number of cells.
        diameter: grain diameter D [m].

    Returns:
        alpha [rad], l1 [m], l2 [m], each shape (n_cells,).
    """
    alpha0 = np.broadcast_to(np.asarray(alpha0_deg, dtype=np.float64), (int(n_cells),))
    bad = ~((alpha0 >= ALPHA_MIN_DEG) & (alpha0 < ALPHA_MAX_DEG))
    if bad.any():
        check_alpha0_deg(alpha0[bad][0])
    alpha = np.radians(alpha0)
    D = np.full(alpha.shape, float(diameter))
    l1, l2 = lengths(D, D, alpha)
    return alpha, l1, l2


# -- the ten-sphere cell (3D, docs/model.md section 14) --------------------------------------

H3_TYPE1_PAIRS = ((1, 2), (1, 6), (3, 4), (4, 5), (1, 7), (1, 10), (4, 8), (4, 9))
"""Type-1 (axial-lateral) contacts of the ten-sphere cell, labels 1..10."""
H3_TYPE2_PAIRS = ((2, 3), (5, 6), (7, 8), (9, 10))
"""Type-2 contacts (parallel to n) of the ten-sphere cell."""
H3_GRAINS = 10
"""Grains of the ten-sphere skeleton; fine grains follow."""
AXISYMMETRIC_KINEMATICS = "axisymmetric_kinematics"
"""Parameter of a 3D cell (``Mesostructure.parameters``): nonzero where the macro strain drives the cell by
its axisymmetric part (``homogenization.material.orientation``, kinematics "axisymmetric"; the kind
``hcell3d-axisym``); its value is the gain on the cell's deviator (``KINEMATICS_GAIN``)."""
KINEMATICS_GAIN = {"axisymmetric": 1.0, "amplified": 2.0}
"""Value of ``AXISYMMETRIC_KINEMATICS`` for each kinematics driven by the axisymmetric part of the strain: the
gain g [-] on the cell's axisymmetric deviator (``homogenization.material.orientation.axisymmetric_map``); the
kind ``hcell3d-axisym`` has 1, ``hcell3d-sand`` 2."""
_TOP_RING = (5, 9, 1, 6)
"""Lateral grains (0-based) at n > 0 in the order of their azimuth about n: 6, 10, 2, 7."""
_BOTTOM_RING = (4, 8, 2, 7)
"""The lateral grains at n < 0 under them: 5, 9, 3, 8."""


def h_cell_3d_faces() -> np.ndarray:
    """Outer triangles (16, 3) of the ten-sphere cell (0-based grains), oriented outwards: four around
    grain 1, four around grain 4, eight on the band between the two rings of lateral grains."""
    faces = []
    for k in range(4):
        top, top_next = _TOP_RING[k], _TOP_RING[(k + 1) % 4]
        bottom, bottom_next = _BOTTOM_RING[k], _BOTTOM_RING[(k + 1) % 4]
        faces += [(0, top, top_next), (3, bottom_next, bottom), (top, bottom, bottom_next), (top, bottom_next, top_next)]
    return np.array(faces, dtype=np.int64)


def h_cell_3d_skeleton(alpha0_deg: float, radius: float, lateral: float = 1.0,
                       plane_angle_deg: float = 90.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Touching ten-sphere cell: radii (10,), centres (10, 3) [m] in (n, t1, t2) about the pore centre, cell size (3,).

    Plane A (grains 1-6) lies in (n, t1); plane B (grains 1, 4, 7-10) is plane A turned about n by
    ``plane_angle_deg`` (90: the plane (n, t2)). Lateral grains have radius ``lateral * radius``; every
    contact of the two hexagons touches (d1 = r (1 + lateral), d2 = 2 r lateral). Cell size: l1 along n,
    and the extents 2 max abs(x_t1), 2 max abs(x_t2) of the lateral grains.
    """
    alpha = np.radians(check_alpha0_deg(alpha0_deg))
    beta = np.radians(plane_angle_deg)
    r_lat = lateral * radius
    d1, d2 = radius + r_lat, 2.0 * r_lat
    top, side = d2 / 2.0 + d1 * np.cos(alpha), d1 * np.sin(alpha)
    c, s = side * np.cos(beta), side * np.sin(beta)
    half = d2 / 2.0
    position = np.array([[top, 0.0, 0.0], [half, -side, 0.0], [-half, -side, 0.0], [-top, 0.0, 0.0],
                         [-half, side, 0.0], [half, side, 0.0],
                         [half, -c, -s], [-half, -c, -s], [-half, c, s], [half, c, s]])
    radii = np.array([radius, r_lat, r_lat, radius] + [r_lat] * 6)
    cell_size = np.array([2.0 * top, 2.0 * np.abs(position[:, 1]).max(), 2.0 * np.abs(position[:, 2]).max()])
    return radii, position, cell_size


def build_h_cell_3d(alpha0_deg: float = CellDefaults.alpha0_deg, *, radius: float = CellDefaults.radius,
                    lateral: float = 1.0, plane_angle_deg: float = 90.0, fines: tuple[float, ...] = (),
                    fine_offsets: tuple[tuple[float, float, float], ...] | None = None,
                    name: str | None = None, axisymmetric: bool = False,
                    kinematics: str | None = None) -> Mesostructure:
    """Ten-sphere H-cell (docs/model.md section 14) with free fine grains in the pore.

    Args:
        alpha0_deg: opening angle [deg]; equal spheres in orthogonal planes need >= 45 deg.
        radius: radius r of the axial grains 1 and 4 [m].
        lateral: radius of the eight lateral grains over r [-].
        plane_angle_deg: angle of plane B (grains 1, 4, 7-10) to plane A (1-6) about n [deg], in (0, 180).
        fines: radius of each fine grain over r [-] (zeros left out).
        fine_offsets: (n, t1, t2) offset of each fine grain from the pore centre over r [-].
        name: its name (default: from the parameters).
        axisymmetric: the kinematics "axisymmetric" (``hcell3d-axisym``) where ``kinematics`` is None.
        kinematics: "projected" or a key of ``KINEMATICS_GAIN``.

    Returns:
        The cell: grains 1, 4 driven, lateral grains driven along t1, t2 only, fine grains free;
        outer surface ``h_cell_3d_faces``.

    Raises:
        MesostructureError: bad parameter, a fine grain outside the pore or overlapping grains."""
    label = name or "3D " + _default_name(alpha0_deg, lateral, fines)
    if kinematics is None:
        kinematics = "axisymmetric" if axisymmetric else "projected"
    if kinematics != "projected" and kinematics not in KINEMATICS_GAIN:
        raise MesostructureError(f"mesostructure {label!r}: kinematics {kinematics!r} is not one of projected, "
                                 f"{', '.join(KINEMATICS_GAIN)}")
    for key, value in (("radius", radius), ("lateral", lateral)):
        if not (math.isfinite(value) and value > 0.0):
            raise MesostructureError(f"mesostructure {label!r}: {key} = {value:g} must be finite and > 0")
    if not (math.isfinite(plane_angle_deg) and 0.0 < plane_angle_deg < 180.0):
        raise MesostructureError(f"mesostructure {label!r}: plane = {plane_angle_deg:g} deg is outside (0, 180)")
    try:
        radii, position, cell_size = h_cell_3d_skeleton(alpha0_deg, radius, lateral, plane_angle_deg)
    except ValueError as exc:
        raise MesostructureError(f"mesostructure {label!r}: {exc}") from None
    lateral_gap = min(np.linalg.norm(position[a] - position[b]) - radii[a] - radii[b]
                      for a, b in ((1, 6), (1, 9), (5, 6), (5, 9)))
    if lateral_gap < -DemSettings.contact_tolerance * 2.0 * radii[1]:
        raise MesostructureError(f"mesostructure {label!r}: at alpha0 = {alpha0_deg:g} deg the lateral grains of the two "
                                 f"planes overlap; this cell needs a larger alpha0, a plane angle nearer 90 deg or "
                                 f"smaller lateral grains")
    faces = h_cell_3d_faces()
    offsets = [(0.0, 0.0, 0.0)] * len(fines) if fine_offsets is None else list(fine_offsets)
    if len(offsets) != len(fines):
        raise MesostructureError(f"mesostructure {label!r}: {len(fines)} fine grains but {len(offsets)} positions")
    fine_radius, fine_position = _place_fines(
        label, fines, offsets, radius, 3, inside=lambda centre: inside_outer(position, faces, centre),
        room=lambda offset: float(np.min(np.linalg.norm(position - np.asarray(offset) * radius, axis=1)
                                         - radii)) / radius,
        where=lambda offset: f"{tuple(offset)}", pore="the pore (the cell's outer surface)", note="")
    n_fines = fine_radius.size
    driven = np.array([[True] * 3] + [[False, True, True]] * 2 + [[True] * 3] + [[False, True, True]] * 6
                      + [[False] * 3] * n_fines)
    pairs = list(combinations(range(H3_GRAINS + n_fines), 2))
    return Mesostructure(name=label, radius=np.concatenate([radii, fine_radius]),
                         position=np.concatenate([position, fine_position]), driven=driven,
                         pairs=np.array(pairs, dtype=np.int64), outer=faces, cell_size=cell_size,
                         pair_label=_labels(label, pairs, H3_TYPE1_PAIRS, H3_TYPE2_PAIRS),
                         parameters={"alpha0_deg": float(alpha0_deg),
                                     **({AXISYMMETRIC_KINEMATICS: KINEMATICS_GAIN[kinematics]}
                                        if kinematics != "projected" else {})})


def plain_h_cell(dim: int, alpha0_deg: float = CellDefaults.alpha0_deg,
                 radius: float = CellDefaults.radius) -> Mesostructure:
    """The touching plain H-cell of dimension ``dim``: ``h_cell`` (six equal disks) for 2,
    ``build_h_cell_3d`` (ten equal spheres in orthogonal planes) for 3, at ``alpha0_deg`` [deg] and
    grain radius ``radius`` [m].

    Raises:
        ValueError: ``dim`` is neither 2 nor 3.
        MesostructureError: the 3D cell's bad parameter (as ``build_h_cell_3d``).
    """
    dimension(dim)
    return h_cell(alpha0_deg, radius) if dim == 2 else build_h_cell_3d(alpha0_deg, radius=radius)


def plain_alpha0_3d(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0_deg, radius) if ``meso`` is the touching ten-equal-sphere cell of orthogonal planes, else None.

    The closed-form 3D backend models exactly this cell; compared to 1e-9 of the radius like
    ``plain_alpha0``.
    """
    return _plain(meso, H3_GRAINS, lambda alpha0, radius: build_h_cell_3d(alpha0, radius=radius))
