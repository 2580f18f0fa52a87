"""Parametric mesostructures: H-cells with unequal grains and fine grains in the pore, and specs.

A mesostructure is named on the command line (``--mesostructure``) and in Python either by
a file (TOML/JSON, ``warp_hcell.mesostructures.mesostructure.load_mesostructure``) or by a *builder spec*:

    SPEC   := KIND [":" KEY "=" VALUE ("," KEY "=" VALUE)*]
    KIND   := "hcell" | "hcell-unequal" | "hcell-fines"

Keys (all optional unless marked):

- ``alpha0=DEG``: initial opening angle [deg], in [30, 90). Given in the spec it fixes the
  geometry; without it the command's ``--alpha0`` (or the sweep's list) is used.
- ``radius=R``: radius r of the axial grains 1 and 4 [m] (default 0.5, D = 1 m).
- ``lateral=RATIO``: radius of the lateral grains 2, 3, 5, 6 over r [-] (default 1;
  required by ``hcell-unequal``). Every contact of the H-cell touches: d1 = r (1 + lateral),
  d2 = 2 r lateral.
- ``ratio=R1/R2/...``: fine grains (required by ``hcell-fines``): radius of each fine grain
  over r [-], "/" between grains; a ratio of 0 means no grain. Fine grains are free along
  n and t (no driven DOF), labelled 7, 8, ... after the six H-cell grains.
- ``n=X1/X2/...``, ``t=Y1/Y2/...``: offset of each fine grain's centre from the pore
  centre along the cell axis n and the lateral direction t, in units of r [-] (default 0:
  the pore centre). One value applies to every grain.

Examples: ``hcell``, ``hcell-unequal:alpha0=55,lateral=0.7``,
``hcell-fines:alpha0=50,ratio=0.76``, ``hcell-fines:ratio=0.3/0.3,n=0.4/-0.4``.
Anything that is not a spec is read as a file path (write ``./hcell`` for a file of that
name). In a comma list of mesostructures (the sweep), a piece ``KEY=VALUE`` without ``:``
continues the spec before it (``split_mesostructure_list``).

Validation (``MesostructureError``, one line): unknown kind or key, malformed values,
grains that overlap by more than the contact tolerance (``DemSettings.contact_tolerance``
of the pair's diameter sum), a fine grain whose centre is outside the pore (the hexagon
1-2-3-4-5-6). ``pore_ratio`` gives the largest fine grain that fits at a position.

This module and ``warp_hcell.mesostructures.mesostructure.h_cell`` are the only code that knows the shape of
these cells; everything else sees a ``Mesostructure``. ``plain_h_cell_alpha0`` tells
whether a mesostructure is the six-equal-grain H-cell (which closed-form backends model);
``h_cell_alpha0`` gives the opening angle of any cell with H-cell labels (for run records).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Mapping

import numpy as np

from warp_hcell.mesostructures.mesostructure import (
    H_TYPE1_PAIRS,
    H_TYPE2_PAIRS,
    Mesostructure,
    MesostructureError,
    h_cell,
    h_cell_reference,
    load_mesostructure,
)
from warp_hcell.core.parameters import CellDefaults, check_alpha0_deg, DemSettings
from warp_hcell.mesostructures import hcell

KINDS = ("hcell", "hcell-unequal", "hcell-fines", "hcell3d", "hcell3d-fines")
"""Builder names accepted as the KIND of a spec."""
KEYS = {
    "hcell": ("alpha0", "radius", "lateral"),
    "hcell-unequal": ("alpha0", "radius", "lateral"),
    "hcell-fines": ("alpha0", "radius", "lateral", "ratio", "n", "t"),
    "hcell3d": ("alpha0", "radius", "lateral", "plane"),
    "hcell3d-fines": ("alpha0", "radius", "lateral", "plane", "ratio", "n", "t1", "t2"),
}
"""Keys each kind accepts."""
REQUIRED = {"hcell": (), "hcell-unequal": ("lateral",), "hcell-fines": ("ratio",), "hcell3d": (),
            "hcell3d-fines": ("ratio",)}
"""Keys each kind needs."""
LIST_KEYS = ("ratio", "n", "t", "t1", "t2")
"""Keys whose value is a "/"-separated list (one value per fine grain)."""
H_GRAINS = 6
"""Grains of the H-cell skeleton (labels 1..6); fine grains follow."""


def h_cell_skeleton(alpha0_deg: float, radius: float, lateral: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        position, cell_size = h_cell_reference(alpha0_deg, radius)
        return np.full(H_GRAINS, float(radius)), position[0], cell_size[0]
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
    radii, position, _ = h_cell_skeleton(alpha0_deg, 1.0, lateral)
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
        fine_offsets: (n, t) offset of each fine grain from the pore centre, in units of r
            [-], one per entry of ``fines`` (default: the pore centre).
        name: mesostructure name (default: describes the parameters).

    Returns:
        Grains 1..6 as in spec section 2 (1, 4 driven along n and t; 2, 3, 5, 6 driven along
        t, free along n), then the fine grains (free along n and t); every pair is a
        candidate contact; type-1/type-2 labels on the skeleton; outer polygon = hexagon.

    Raises:
        MesostructureError: bad parameter, a fine grain outside the pore, or overlapping
            grains (one line).
    """
    label = name or _default_name(alpha0_deg, lateral, fines)
    for key, value in (("radius", radius), ("lateral", lateral)):
        if not (math.isfinite(value) and value > 0.0):
            raise MesostructureError(f"mesostructure {label!r}: {key} = {value:g} must be finite and > 0")
    try:
        radii, position, cell_size = h_cell_skeleton(alpha0_deg, radius, lateral)
    except ValueError as exc:
        raise MesostructureError(f"mesostructure {label!r}: {exc}") from None
    offsets = [(0.0, 0.0)] * len(fines) if fine_offsets is None else list(fine_offsets)
    if len(offsets) != len(fines):
        raise MesostructureError(f"mesostructure {label!r}: {len(fines)} fine grains but {len(offsets)} positions")
    hexagon = position[[0, 1, 2, 3, 4, 5]]
    fine_radius, fine_position = [], []
    for k, (ratio, (dn, dt)) in enumerate(zip(fines, offsets)):
        if not (math.isfinite(ratio) and ratio >= 0.0) or not (math.isfinite(dn) and math.isfinite(dt)):
            raise MesostructureError(f"mesostructure {label!r}: fine grain {k + 1} needs a finite ratio >= 0 "
                                     f"and a finite position, got ratio={ratio:g}, n={dn:g}, t={dt:g}")
        if ratio == 0.0:
            continue
        centre = np.array([dn, dt]) * radius
        if not _inside(hexagon, centre):
            raise MesostructureError(f"mesostructure {label!r}: fine grain at n={dn:g}, t={dt:g} (units of r) "
                                     f"is outside the pore (hexagon 1-2-3-4-5-6)")
        room = pore_ratio(alpha0_deg, lateral=lateral, n=dn, t=dt)
        if ratio > room * (1.0 + DemSettings.contact_tolerance):
            raise MesostructureError(f"mesostructure {label!r}: fine grain ratio {ratio:g} does not fit the pore at "
                                     f"n={dn:g}, t={dt:g}: the largest is {room:.6g} (alpha0 = {alpha0_deg:g} deg)")
        fine_radius.append(min(ratio, room) * radius)
        fine_position.append(centre)
    n_fines = len(fine_radius)
    all_radius = np.concatenate([radii, fine_radius])
    all_position = np.concatenate([position, np.reshape(fine_position, (n_fines, 2))])
    driven = np.array([[True, True]] + [[False, True]] * 2 + [[True, True]] + [[False, True]] * 2
                      + [[False, False]] * n_fines)
    pairs = list(combinations(range(H_GRAINS + n_fines), 2))
    labels = {(a - 1, b - 1): 1 for a, b in H_TYPE1_PAIRS} | {(a - 1, b - 1): 2 for a, b in H_TYPE2_PAIRS}
    return Mesostructure(name=label, radius=all_radius, position=all_position, driven=driven,
                         pairs=np.array(pairs, dtype=np.int64), outer=np.arange(H_GRAINS), cell_size=cell_size,
                         pair_type=np.array([labels.get(p, 0) for p in pairs]))


def build_h_cell_3d(alpha0_deg: float = CellDefaults.alpha0_deg, *, radius: float = CellDefaults.radius,
                    lateral: float = 1.0, plane_angle_deg: float = 90.0, fines: tuple[float, ...] = (),
                    fine_offsets: tuple[tuple[float, float, float], ...] | None = None,
                    name: str | None = None) -> Mesostructure:
    """Ten-sphere H-cell (docs/model.md section 14) with free fine grains in the pore.

    Args:
        alpha0_deg: opening angle [deg]; equal spheres in planes 90 deg apart need >= 45 deg (below,
            the lateral grains of the two planes overlap).
        radius: radius r of the axial grains 1 and 4 [m].
        lateral: radius of the eight lateral grains over r [-].
        plane_angle_deg: angle between plane A (grains 1-6, (n, t1)) and plane B (grains 1, 4,
            7-10) about n [deg], in (0, 180); 90 is the orthogonal cell.
        fines: radius of each fine grain over r [-]; zeros are left out.
        fine_offsets: (n, t1, t2) offset of each fine grain from the pore centre in units of r [-]
            (default: the centre).
        name: mesostructure name (default: describes the parameters).

    Returns:
        Grains 1, 4 driven along n, t1, t2; grains 2, 3, 5, 6, 7, 8, 9, 10 driven along t1 and t2
        (homothetically with l2, l3) and free along n; fine grains free along every axis; every
        pair a candidate; type-1/type-2 labels on the skeleton; outer surface: the sixteen
        triangles of ``hcell.h_cell_3d_faces``.

    Raises:
        MesostructureError: bad parameter, a fine grain outside the pore or overlapping grains (one line).
    """
    label = name or "3D " + _default_name(alpha0_deg, lateral, fines)
    for key, value in (("radius", radius), ("lateral", lateral)):
        if not (math.isfinite(value) and value > 0.0):
            raise MesostructureError(f"mesostructure {label!r}: {key} = {value:g} must be finite and > 0")
    if not (math.isfinite(plane_angle_deg) and 0.0 < plane_angle_deg < 180.0):
        raise MesostructureError(f"mesostructure {label!r}: plane = {plane_angle_deg:g} deg is outside (0, 180)")
    try:
        radii, position, cell_size = hcell.h_cell_3d_skeleton(alpha0_deg, radius, lateral, plane_angle_deg)
    except ValueError as exc:
        raise MesostructureError(f"mesostructure {label!r}: {exc}") from None
    lateral_gap = min(np.linalg.norm(position[a] - position[b]) - radii[a] - radii[b]
                      for a, b in ((1, 6), (1, 9), (5, 6), (5, 9)))
    if lateral_gap < -DemSettings.contact_tolerance * 2.0 * radii[1]:
        raise MesostructureError(f"mesostructure {label!r}: at alpha0 = {alpha0_deg:g} deg the lateral grains of the two "
                                 f"planes overlap; this cell needs a larger alpha0, a plane angle nearer 90 deg or "
                                 f"smaller lateral grains")
    faces = hcell.h_cell_3d_faces()
    offsets = [(0.0, 0.0, 0.0)] * len(fines) if fine_offsets is None else list(fine_offsets)
    if len(offsets) != len(fines):
        raise MesostructureError(f"mesostructure {label!r}: {len(fines)} fine grains but {len(offsets)} positions")
    fine_radius, fine_position = [], []
    for k, (ratio, offset) in enumerate(zip(fines, offsets)):
        if not (math.isfinite(ratio) and ratio >= 0.0) or not all(math.isfinite(v) for v in offset):
            raise MesostructureError(f"mesostructure {label!r}: fine grain {k + 1} needs a finite ratio >= 0 and a "
                                     f"finite position")
        if ratio == 0.0:
            continue
        centre = np.asarray(offset, dtype=np.float64) * radius
        a, b, c = (position[faces[:, m]] for m in range(3))
        if not np.all(np.einsum("fi,fi->f", np.cross(b - a, c - a), centre - a) < 0.0):
            raise MesostructureError(f"mesostructure {label!r}: fine grain at {tuple(offset)} (units of r) is outside "
                                     f"the pore (the cell's outer surface)")
        room = float(np.min(np.linalg.norm(position - centre, axis=1) - radii)) / radius
        if ratio > room * (1.0 + DemSettings.contact_tolerance):
            raise MesostructureError(f"mesostructure {label!r}: fine grain ratio {ratio:g} does not fit the pore at "
                                     f"{tuple(offset)}: the largest is {room:.6g}")
        fine_radius.append(min(ratio, room) * radius)
        fine_position.append(centre)
    n_fines = len(fine_radius)
    driven = np.array([[True] * 3] + [[False, True, True]] * 2 + [[True] * 3] + [[False, True, True]] * 6
                      + [[False] * 3] * n_fines)
    pairs = list(combinations(range(hcell.H3_GRAINS + n_fines), 2))
    labels = ({(a - 1, b - 1): 1 for a, b in hcell.H3_TYPE1_PAIRS}
              | {tuple(sorted((a - 1, b - 1))): 2 for a, b in hcell.H3_TYPE2_PAIRS})
    return Mesostructure(name=label, radius=np.concatenate([radii, fine_radius]),
                         position=np.concatenate([position, np.reshape(fine_position, (n_fines, 3))]), driven=driven,
                         pairs=np.array(pairs, dtype=np.int64), outer=faces, cell_size=cell_size,
                         pair_type=np.array([labels.get(p, 0) for p in pairs]))


def plain_h_cell_3d_alpha0(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0_deg, radius) if ``meso`` is the touching ten-equal-sphere cell of orthogonal planes, else None.

    The closed-form 3D backend models exactly this cell; compared to 1e-9 of the radius like
    ``plain_h_cell_alpha0``.
    """
    if meso.dim != 3 or meso.n_grains != hcell.H3_GRAINS or not np.allclose(meso.radius, meso.radius[0], rtol=1e-12,
                                                                             atol=0.0):
        return None
    branch = meso.position[1] - meso.position[0]
    alpha0 = round(math.degrees(math.atan2(-branch[1], -branch[0])), 9)
    radius = float(meso.radius[0])
    try:
        reference = build_h_cell_3d(alpha0, radius=radius)
    except (ValueError, MesostructureError):
        return None
    same = (np.allclose(meso.position, reference.position, rtol=0.0, atol=1e-9 * radius)
            and np.allclose(meso.cell_size, reference.cell_size, rtol=0.0, atol=1e-9 * radius)
            and np.array_equal(meso.driven, reference.driven) and np.array_equal(meso.outer, reference.outer)
            and np.array_equal(meso.pairs, reference.pairs) and np.array_equal(meso.pair_type, reference.pair_type))
    return (alpha0, radius) if same else None


def _default_name(alpha0_deg: float, lateral: float, fines: tuple[float, ...]) -> str:
    parts = [f"h-cell alpha0={float(alpha0_deg):g} deg"]
    if lateral != 1.0:
        parts.append(f"lateral/r={lateral:g}")
    if any(f > 0.0 for f in fines):
        parts.append("fines r_f/r=" + "/".join(f"{f:g}" for f in fines))
    return ", ".join(parts)


def _inside(polygon: np.ndarray, point: np.ndarray) -> bool:
    """True if ``point`` lies strictly inside the convex ``polygon`` (ordered vertices)."""
    edge = np.roll(polygon, -1, axis=0) - polygon
    rel = point - polygon
    cross = edge[:, 0] * rel[:, 1] - edge[:, 1] * rel[:, 0]
    return bool(np.all(cross > 0.0) or np.all(cross < 0.0))


def h_cell_alpha0(meso: Mesostructure) -> float | None:
    """Initial opening angle [deg] of a cell with H-cell labels, or None without them.

    The angle between the axis n and the branch 1 -> 2 of the reference type-1 contact, in
    the reference geometry, rounded to 1e-9 deg (so that the cell built at ``alpha0`` gives
    back exactly ``alpha0`` for any value with at most nine decimals).
    """
    if not meso.is_h_cell:
        return None
    branch = meso.position[1] - meso.position[0]
    return round(math.degrees(math.atan2(-branch[1], -branch[0])), 9)


def plain_h_cell_alpha0(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0_deg, radius) if ``meso`` is the touching six-equal-grain H-cell, else None.

    The closed-form backends model exactly this cell; the comparison is to 1e-9 of the
    grain radius on positions, cell size, driven flags, pairs, labels and outer polygon.
    """
    if meso.n_grains != H_GRAINS or not np.allclose(meso.radius, meso.radius[0], rtol=1e-12, atol=0.0):
        return None
    alpha0 = h_cell_alpha0(meso)
    if alpha0 is None:
        return None
    radius = float(meso.radius[0])
    try:
        reference = h_cell(alpha0, radius)
    except ValueError:
        return None
    same = (np.allclose(meso.position, reference.position, rtol=0.0, atol=1e-9 * radius)
            and np.allclose(meso.cell_size, reference.cell_size, rtol=0.0, atol=1e-9 * radius)
            and np.array_equal(meso.driven, reference.driven) and np.array_equal(meso.outer, reference.outer)
            and {tuple(p): t for p, t in zip(meso.pairs.tolist(), meso.pair_type.tolist())}
            == {tuple(p): t for p, t in zip(reference.pairs.tolist(), reference.pair_type.tolist())})
    return (alpha0, radius) if same else None


@dataclass(frozen=True)
class MesostructureSource:
    """A mesostructure as named by the user: a builder spec or a file, not yet built.

    Attributes:
        text: the text as given (spec or path).
        kind: builder name (one of ``KINDS``), or None for a file.
        options: parsed spec keys -> values (floats, or tuples of floats for list keys).
    """

    text: str
    kind: str | None
    options: tuple[tuple[str, float | tuple[float, ...]], ...] = ()

    @property
    def fixed_alpha0(self) -> float | None:
        """alpha0 [deg] fixed by the spec, or None (files, and specs without alpha0)."""
        return dict(self.options).get("alpha0")  # type: ignore[return-value]

    @property
    def takes_alpha0(self) -> bool:
        """True for a spec whose alpha0 comes from the command (a file fixes its geometry)."""
        return self.kind is not None and self.fixed_alpha0 is None

    @property
    def label(self) -> str:
        """Short name for folders and legends: the spec text, or the file's stem."""
        return self.text if self.kind is not None else Path(self.text).stem

    def build(self, alpha0_deg: float | None = None) -> Mesostructure:
        """The mesostructure; ``alpha0_deg`` is used by specs without their own alpha0.

        Raises:
            MesostructureError: unreadable file or invalid geometry (one line).
        """
        if self.kind is None:
            return load_mesostructure(self.text)
        opts: Mapping[str, float | tuple[float, ...]] = dict(self.options)
        alpha0 = opts.get("alpha0", CellDefaults.alpha0_deg if alpha0_deg is None else alpha0_deg)
        fines = tuple(opts.get("ratio", ()))  # type: ignore[arg-type]
        n_fines = len(fines)
        spatial = self.kind.startswith("hcell3d")
        offsets = None
        if n_fines:
            axes = ("n", "t1", "t2") if spatial else ("n", "t")
            offsets = tuple(zip(*(_per_grain(self.text, key, opts.get(key, (0.0,)), n_fines) for key in axes)))
        size = {"radius": float(opts.get("radius", CellDefaults.radius)),  # type: ignore[arg-type]
                "lateral": float(opts.get("lateral", 1.0))}  # type: ignore[arg-type]
        if spatial:
            return build_h_cell_3d(float(alpha0), **size, plane_angle_deg=float(opts.get("plane", 90.0)),  # type: ignore[arg-type]
                                   fines=fines, fine_offsets=offsets, name=self.text)
        return build_h_cell(float(alpha0), **size, fines=fines, fine_offsets=offsets, name=self.text)

    def __str__(self) -> str:
        return self.text


def _per_grain(text: str, key: str, values, n_fines: int) -> tuple[float, ...]:
    values = tuple(values)
    if len(values) == 1:
        return values * n_fines
    if len(values) != n_fines:
        raise MesostructureError(f"mesostructure {text!r}: {key} has {len(values)} values for {n_fines} fine grains")
    return values


def parse_mesostructure(text: str) -> MesostructureSource:
    """Parse a spec (grammar in the module docstring) or take ``text`` as a file path.

    Only the syntax is checked here (and that a file exists); ``build`` validates geometry.

    Raises:
        MesostructureError: malformed spec, or a path that is not a file (one line).
    """
    text = str(text).strip()
    kind, _, body = text.partition(":")
    if kind in KINDS:
        options: dict[str, float | tuple[float, ...]] = {}
        for item in filter(None, (piece.strip() for piece in body.split(","))):
            key, sep, value = (part.strip() for part in item.partition("="))
            if not sep or not value:
                raise MesostructureError(f"mesostructure {text!r}: {item!r} is not KEY=VALUE")
            if key not in KEYS[kind]:
                raise MesostructureError(f"mesostructure {text!r}: unknown key {key!r} for {kind}; "
                                         f"allowed: {', '.join(KEYS[kind])}")
            if key in options:
                raise MesostructureError(f"mesostructure {text!r}: key {key!r} given twice")
            try:
                numbers = tuple(float(v) for v in value.split("/"))
            except ValueError:
                raise MesostructureError(f"mesostructure {text!r}: {key}={value!r} is not a number"
                                         + (" list (a/b/...)" if key in LIST_KEYS else "")) from None
            if not all(math.isfinite(v) for v in numbers):
                raise MesostructureError(f"mesostructure {text!r}: {key}={value!r} is not finite")
            if key not in LIST_KEYS and len(numbers) != 1:
                raise MesostructureError(f"mesostructure {text!r}: {key} takes one value, got {value!r}")
            options[key] = numbers if key in LIST_KEYS else numbers[0]
        missing = [key for key in REQUIRED[kind] if key not in options]
        if missing:
            raise MesostructureError(f"mesostructure {text!r}: {kind} needs {missing[0]}=...")
        if "alpha0" in options:
            try:
                check_alpha0_deg(options["alpha0"])  # type: ignore[arg-type]
            except ValueError as exc:
                raise MesostructureError(f"mesostructure {text!r}: {exc}") from None
        return MesostructureSource(text, kind, tuple(options.items()))
    if not Path(text).is_file():
        raise MesostructureError(f"mesostructure {text!r} is neither a file nor a spec ({' | '.join(KINDS)}[:KEY=VALUE,...])")
    return MesostructureSource(text, None)


def resolve_mesostructure(text: str, alpha0_deg: float | None = None) -> Mesostructure:
    """The mesostructure named by ``text`` (file path or spec), built at ``alpha0_deg`` if it needs one."""
    return parse_mesostructure(text).build(alpha0_deg)


def split_mesostructure_list(text: str) -> list[str]:
    """Split a comma list of mesostructures; a ``KEY=VALUE`` piece without ``:`` joins the spec before it.

    ``"hcell,hcell-fines:alpha0=50,ratio=0.7,data/x.toml"`` -> ``["hcell",
    "hcell-fines:alpha0=50,ratio=0.7", "data/x.toml"]``.
    """
    items: list[str] = []
    for piece in (p.strip() for p in str(text).split(",")):
        if not piece:
            continue
        continues = "=" in piece and ":" not in piece and items and items[-1].partition(":")[0] in KINDS
        if continues:
            items[-1] = f"{items[-1]},{piece}" if ":" in items[-1] else f"{items[-1]}:{piece}"
        else:
            items.append(piece)
    return items


def mesostructure_arg(text: str) -> MesostructureSource:
    """argparse type: a spec or a file (see the module docstring); one-line error otherwise."""
    try:
        return parse_mesostructure(text)
    except MesostructureError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def mesostructure_list_arg(text: str) -> list[MesostructureSource]:
    """argparse type: comma list of specs and files (``split_mesostructure_list``)."""
    items = split_mesostructure_list(text)
    if not items:
        raise argparse.ArgumentTypeError("empty mesostructure list")
    return [mesostructure_arg(item) for item in items]


MESOSTRUCTURE_HELP = (
    "mesostructure: a TOML/JSON file, or a builder spec KIND[:KEY=VALUE,...] with KIND hcell | hcell-unequal | "
    "hcell-fines (2D) or hcell3d | hcell3d-fines (3D, ten spheres) and keys alpha0 (deg; default: --alpha0), "
    "radius (r of grains 1, 4 [m]), lateral (radius of the lateral grains / r), plane (3D: angle between the two "
    "planes, deg), ratio (fine-grain radius / r, 'a/b' for several), n, t (2D) or n, t1, t2 (3D) (fine-grain "
    "offset from the pore centre / r); e.g. hcell-fines:alpha0=50,ratio=0.76 or hcell3d:alpha0=55")
"""--help text shared by every command that takes --mesostructure."""
