"""Shear band of a specimen measured from its Gauss-point deviatoric strain.

``measure_band(points, weights, eps_d)`` finds the band as the region of the larger values,
its axis by a weighted principal-axis fit, and its width from the profile across the axis:

1. Points with eps_d >= ``threshold`` x max(eps_d) give the axis: weights area x eps_d,
   centroid c, principal direction d (largest second moment); the angle is that of d from the
   x axis (lateral, the minor principal stress direction of a biaxial test), in [0, 90] deg.
2. Profile: the points whose coordinate along d lies within ``core`` x the band's half-length
   of c (the ends, near the specimen's faces, are left out) are binned by their distance s
   to the axis in bins of width ``bin_width``; each bin holds the area-weighted mean of eps_d.
   Background: the area-weighted median of eps_d of those points; the width is the full width
   at half maximum of (profile - background), the two half-maximum crossings found by linear
   interpolation between bins.

Units: positions and widths in the positions' unit [m]; angles [deg].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Band:
    """A measured band.

    Attributes:
        width: full width at half maximum of the profile across the band [m].
        angle_deg: inclination of the band axis from the x axis [deg], in [0, 90].
        centre: a point of the axis [m], shape (2,).
        peak: maximum of the profile above the background [-].
        background: eps_d away from the band (area-weighted median) [-].
        profile_s: bin centres across the band [m]; profile: their mean eps_d [-].
    """

    width: float
    angle_deg: float
    centre: np.ndarray
    peak: float
    background: float
    profile_s: np.ndarray
    profile: np.ndarray


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def measure_band(points: np.ndarray, weights: np.ndarray, eps_d: np.ndarray, *, bin_width: float,
                 threshold: float = 0.5, core: float = 0.5, region: np.ndarray | None = None) -> Band:
    """Band axis, angle and width of the field ``eps_d`` (module docstring).

    Args:
        points: Gauss-point positions [m], shape (n, 2).
        weights: Gauss-point areas [m^2], shape (n,).
        eps_d: deviatoric strain (or its increment) at the points [-], shape (n,), >= 0.
        bin_width: bin width of the profile across the band [m], > 0.
        threshold: fraction of max(eps_d) above which a point belongs to the band's axis fit.
        core: fraction of the band's half-length kept for the profile.
        region: optional bool mask, shape (n,): only these points are used (one branch of
            crossing or reflected bands).

    Raises:
        ValueError: eps_d has no positive value, or the profile has no half-maximum crossing
            on one side (the band reaches the specimen's edge).
    """
    points, weights, eps_d = (np.asarray(a, dtype=np.float64) for a in (points, weights, eps_d))
    if region is not None:
        points, weights, eps_d = points[region], weights[region], eps_d[region]
    top = float(eps_d.max())
    if not top > 0.0:
        raise ValueError("no positive deviatoric strain: no band")
    inside = eps_d >= threshold * top
    w = weights[inside] * eps_d[inside]
    centre = (w @ points[inside]) / w.sum()
    r = points[inside] - centre
    moment = (r * w[:, None]).T @ r
    values, vectors = np.linalg.eigh(moment)
    d = vectors[:, -1]
    normal = np.array([-d[1], d[0]])
    angle = float(np.degrees(np.arctan2(abs(d[1]), abs(d[0]))))
    along = (points - centre) @ d
    half_length = float(np.abs(r @ d).max())
    keep = np.abs(along) <= core * half_length
    s = (points[keep] - centre) @ normal
    background = _weighted_median(eps_d[keep], weights[keep])
    edges = np.arange(np.floor(s.min() / bin_width), np.ceil(s.max() / bin_width) + 1) * bin_width
    index = np.clip(np.digitize(s, edges) - 1, 0, edges.size - 2)
    area = np.bincount(index, weights[keep], minlength=edges.size - 1)
    total = np.bincount(index, weights[keep] * eps_d[keep], minlength=edges.size - 1)
    filled = area > 0.0
    centres = 0.5 * (edges[:-1] + edges[1:])[filled]
    profile = total[filled] / area[filled]
    excess = profile - background
    k = int(np.argmax(excess))
    half = 0.5 * excess[k]
    crossings = []
    for direction in (-1, 1):
        j = k
        while 0 <= j + direction < excess.size and excess[j + direction] > half:
            j += direction
        if not 0 <= j + direction < excess.size:
            raise ValueError("the band profile has no half-maximum crossing on one side")
        a, b = excess[j], excess[j + direction]
        crossings.append(centres[j] + (centres[j + direction] - centres[j]) * (a - half) / (a - b))
    return Band(float(abs(crossings[1] - crossings[0])), angle, centre, float(excess[k]), background, centres, profile)
