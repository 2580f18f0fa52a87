"""Density as the state: the map between a void ratio e and the cell's initial opening angle alpha0.

Rule (linear in alpha0): the densest cell (opening ``alpha_dense_deg``) stands for ``e_min``, the
loosest (``alpha_loose_deg``) for ``e_max``, and in between alpha0 is linear in the relative density
Dr = (e_max - e) / (e_max - e_min)::

    alpha0 = alpha_loose - Dr (alpha_loose - alpha_dense)

e_min and e_max are material parameters (``hmodel calibrate`` fits them); the two angles are the
cell's (``OPENING_RANGE_DEG``, by dimension). e is the void ratio of the force-free initial cell;
under the macro strain it follows e = (1 + e0) J - 1, J = V / V0 the volume ratio (compression
positive: J < 1 and e falls in contraction).

- ``DensityMap``: the map, with ``alpha0_deg(e)``, ``void_ratio(alpha0)``, ``to_dict``/``from_dict``;
- ``default_map(dim, e_min, e_max)``: the map of the plain cell of ``dim``;
- ``opening_angle_deg(e, e_min, e_max, alpha_dense, alpha_loose)``: the rule on arrays (NaN outside;
  ``line_angle_deg`` the same line extended);
- ``current_void_ratio(e0, J)``; ``initial_void_ratio(alpha0, dim)``: e0 of a run given alpha0 only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from warp_hcell.core.errors import UserError

DEFAULT_E_MIN = 0.597
"""Void ratio of the densest cell when not given [-] (Toyoura sand's minimum void ratio)."""
DEFAULT_E_MAX = 0.977
"""Void ratio of the loosest cell when not given [-] (Toyoura sand's maximum void ratio)."""
OPENING_RANGE_DEG = {2: (40.0, 56.0), 3: (47.0, 55.3)}
"""Dimension -> (alpha_dense, alpha_loose) [deg] of the cell. Loose: the widest opening that still
liquefies (undrained from 2e5, phi_g = 30 deg; wider cells stiffen again), rounded inwards: 56 deg for
the planar cell, 55.3 deg for ``hcell3d-sand`` (DEM and closed form), so that the map's loose third
liquefies (docs/studies/density_map_range.md). Dense: the planar studies' dense cell (40 deg) and the
dense ten-sphere cell (47 deg; below 45 its planes overlap)."""


@dataclass(frozen=True)
class DensityMap:
    """The map between void ratio [-] and initial opening angle [deg] (module docstring).

    Raises (construction):
        ValueError: not 0 <= e_min < e_max (finite), or not 30 <= alpha_dense < alpha_loose < 90 deg.
    """

    e_min: float
    """Void ratio of the densest cell [-], >= 0."""
    e_max: float
    """Void ratio of the loosest cell [-], > e_min."""
    alpha_dense_deg: float
    """Opening angle of the densest cell [deg]."""
    alpha_loose_deg: float
    """Opening angle of the loosest cell [deg], > alpha_dense_deg."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.e_min) and math.isfinite(self.e_max) and 0.0 <= self.e_min < self.e_max):
            raise ValueError(f"void ratio map: needs 0 <= e_min < e_max, got e_min = {self.e_min:g}, "
                             f"e_max = {self.e_max:g}")
        if not 30.0 <= self.alpha_dense_deg < self.alpha_loose_deg < 90.0:
            raise ValueError(f"void ratio map: needs 30 <= alpha_dense < alpha_loose < 90 deg, got "
                             f"{self.alpha_dense_deg:g} and {self.alpha_loose_deg:g}")

    def check(self, e: float, what: str = "void ratio") -> float:
        """``e`` as float if it lies in [e_min, e_max]; else UserError, one line naming ``what``."""
        value = float(e)
        if not (math.isfinite(value) and value >= 0.0):
            raise UserError(f"{what} {value:g}: a void ratio is a finite number >= 0")
        if not self.e_min <= value <= self.e_max:
            raise UserError(f"{what} {value:g} is outside the void ratio map's [e_min, e_max] = "
                            f"[{self.e_min:g}, {self.e_max:g}]; give --e-min/--e-max that hold it")
        return value

    def alpha0_deg(self, e: float) -> float:
        """Initial opening angle [deg] of void ratio ``e`` [-]; UserError (one line) outside [e_min, e_max]."""
        value = self.check(e)
        return float(opening_angle_deg(value, self.e_min, self.e_max, self.alpha_dense_deg, self.alpha_loose_deg))

    def void_ratio(self, alpha0_deg: float) -> float:
        """Void ratio [-] of opening angle ``alpha0_deg`` [deg] (the inverse of ``alpha0_deg``; beyond
        [alpha_dense, alpha_loose] the same line extended, which ``contains`` tells)."""
        a = float(alpha0_deg)
        dr = (self.alpha_loose_deg - a) / (self.alpha_loose_deg - self.alpha_dense_deg)
        return self.e_max - dr * (self.e_max - self.e_min)

    def contains(self, alpha0_deg: float) -> bool:
        """Whether ``alpha0_deg`` [deg] lies within [alpha_dense, alpha_loose]."""
        return self.alpha_dense_deg <= float(alpha0_deg) <= self.alpha_loose_deg

    def to_dict(self) -> dict[str, float]:
        """The four parameters by field name (run files, posterior.json)."""
        return {name: float(value) for name, value in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "DensityMap":
        """Inverse of ``to_dict``."""
        return cls(**{name: float(data[name]) for name in ("e_min", "e_max", "alpha_dense_deg", "alpha_loose_deg")})


def default_map(dim: int, e_min: float = DEFAULT_E_MIN, e_max: float = DEFAULT_E_MAX) -> DensityMap:
    """The map of the plain cell of dimension ``dim`` (``OPENING_RANGE_DEG``) between ``e_min`` and ``e_max``.

    Raises:
        ValueError: ``dim`` not 2 or 3, or a bad pair (``DensityMap``).
    """
    if dim not in OPENING_RANGE_DEG:
        raise ValueError(f"dimension {dim} is neither 2 nor 3")
    return DensityMap(float(e_min), float(e_max), *OPENING_RANGE_DEG[dim])


def line_angle_deg(e: Any, e_min: Any, e_max: Any, alpha_dense_deg: Any, alpha_loose_deg: Any) -> np.ndarray:
    """The rule's line on arrays (broadcast): the opening angle [deg] of void ratios ``e``, extended beyond
    [e_min, e_max] (the critical-state renewal's a(e))."""
    e, lo, hi = (np.asarray(v, dtype=np.float64) for v in (e, e_min, e_max))
    dense, loose = np.asarray(alpha_dense_deg, dtype=np.float64), np.asarray(alpha_loose_deg, dtype=np.float64)
    return dense + (e - lo) / (hi - lo) * (loose - dense)


def opening_angle_deg(e: Any, e_min: Any, e_max: Any, alpha_dense_deg: Any, alpha_loose_deg: Any) -> np.ndarray:
    """The rule on arrays (broadcast): alpha0 [deg] of void ratios ``e``; NaN where e is outside [e_min, e_max]
    or e_min >= e_max (a calibration's sets whose map cannot hold its test)."""
    e, lo, hi = (np.asarray(v, dtype=np.float64) for v in (e, e_min, e_max))
    ok = (lo <= e) & (e <= hi) & (lo < hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        alpha = line_angle_deg(e, lo, hi, alpha_dense_deg, alpha_loose_deg)
    return np.where(ok, alpha, np.nan)


def current_void_ratio(e0: Any, J: Any) -> np.ndarray:
    """Void ratio [-] after the volume ratio ``J`` = V / V0 [-] from the state of void ratio ``e0`` (both
    broadcast): (1 + e0) J - 1 (NaN where e0 is NaN)."""
    return (1.0 + np.asarray(e0, dtype=np.float64)) * np.asarray(J, dtype=np.float64) - 1.0


def initial_void_ratio(alpha0_deg: float | None, dim: int) -> float:
    """e0 [-] that the default map (``default_map(dim)``) gives a cell of opening ``alpha0_deg``; NaN where
    alpha0 is None, NaN or outside the map's angles (a run given alpha0 only)."""
    m = default_map(dim)
    if alpha0_deg is None or not m.contains(alpha0_deg):
        return float("nan")
    return m.void_ratio(float(alpha0_deg))
