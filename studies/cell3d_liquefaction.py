"""Why the ten-sphere cell does not liquefy: single cells on the undrained triaxial path.

Runs the closed form of the 3D cell (``homogenization.backends.analytical.Analytical3DCell``) through an
isotropic compression to p0 and an isochoric triaxial compression, with its own short loop
(strain control only, so every cell's state is at hand), and prints:

- p/p0 along the shear stage, for each alpha0 and cell kind asked;
- the in-plane strain ratio r = d_eps_t / d_eps_n that each plane (n, t1) and (n, t2) of each
  cell sees on that path (2D: r = -1 for every cell), and the plane's area strain;
- the share of p carried by the cells grouped by the angle of their axis to the axial
  direction, and the opening angle of the planes, at a few axial strains;
- the rigid-mechanism ratio r_mech(alpha) of a planar H-cell (d1, d2 fixed), which decides
  whether an imposed ratio r opens (|r| > |r_mech|) or loads (|r| < |r_mech|) a plane.

- with ``--by-axis``: the share of p, the opening angles, the closed contacts and the sliding ratio
  T1/N1 of the cells grouped by |n.e1| of their axis, at 5 and 15 % (which cells hold the pressure
  at a window's edge; docs/studies/liquefaction_3d_cell.md); ``--gain G`` drives an axisymmetric
  kind with the cell deviator multiplied by G (``orientation.axisymmetric_map``).

Usage: python studies/cell3d_liquefaction.py [--alpha0 55,65,75] [--kind hcell3d,hcell3d-volumetric]
       [--order 11] [--spins 4] [--p0 2e5] [--increment 1e-3] [--eps-max 0.15] [--phi-g 30]
       [--by-axis] [--gain G]
Units: stresses in Pa, strains [-], compression positive.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from homogenization.backends.analytical import Analytical3DCell
from homogenization.material.orientation import average_moment, initial_volume, localise
from homogenization.material import orientation as orientation_module
from homogenization.material.orientation import cell_kinematics, orientations_3d
from warp_hcell.core.parameters import CellDefaults, ContactLaw
from warp_hcell.mesostructures.builders import resolve_mesostructure


def mean_pressure(orient, moment: np.ndarray, volume: float) -> float:
    """p = tr(sigma)/3 [Pa] from the per-cell moments (N, 3, 3) [N m] and the macro volume [m^3]."""
    s = average_moment(orient, moment) / volume
    return float(s[:3].sum() / 3.0)


def run_path(spec: str, alpha0: float, *, order: int, spins: int, p0: float, increment: float, eps_max: float,
             phi_g_deg: float = ContactLaw.phi_g_deg, probes: tuple[float, ...] = (0.02, 0.05, 0.10, 0.15)) -> dict:
    """Isotropic compression to p0 (strain steps, the last bisected to 1e-6 of p0), then isochoric triaxial
    compression to ``eps_max``; returns the curve and the states at ``probes`` [-]."""
    meso = resolve_mesostructure(spec, alpha0)
    orient = orientations_3d(order, spins, spin_period_deg=meso.spin_period_deg(), kinematics=cell_kinematics(meso))
    cell = Analytical3DCell(ContactLaw(phi_g_deg=phi_g_deg), CellDefaults.radius)
    state = cell.init_state(meso, orient.n_cells)
    v0 = initial_volume(orient, cell.response(state).area)
    j = 1.0

    def iso(state, j, de):
        new, resp = cell.step(state, localise(orient, np.array([de, de, de, 0, 0, 0])))
        jn = j * (1 - de) ** 3
        return new, jn, mean_pressure(orient, resp.moment, v0 * jn)

    de = 2e-5
    p = 0.0
    while True:
        trial, jt, pt = iso(state, j, de)
        if pt >= p0:
            break
        state, j, p = trial, jt, pt
    lo, hi = 0.0, de
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        trial, jt, pt = iso(state, j, mid)
        if abs(pt - p0) <= 1e-6 * p0:
            break
        lo, hi = (mid, hi) if pt < p0 else (lo, mid)
    state, j = trial, jt
    iso_state = state
    e_lat = 1.0 - 1.0 / math.sqrt(1.0 - increment)
    d_eps = np.array([increment, e_lat, e_lat, 0, 0, 0])
    local = localise(orient, d_eps)
    n_steps = int(round(eps_max / increment))
    curve, snaps = [], {}
    for k in range(1, n_steps + 1):
        state, resp = cell.step(state, local)
        j *= (1 - increment) * (1 - e_lat) ** 2
        curve.append((k * increment, mean_pressure(orient, resp.moment, v0 * j) / p0))
        for eps in probes:
            if abs(k * increment - eps) < 0.5 * increment:
                snaps[eps] = (state, resp.moment.copy(), v0 * j)
    return {"curve": np.array(curve), "orient": orient, "cell": cell, "local": local, "snaps": snaps,
            "iso_state": iso_state, "eps_iso": None, "increment": increment}


def mechanism_ratio(alpha_deg: np.ndarray) -> np.ndarray:
    """d_eps_t / d_eps_n of a rigid planar H-cell (d1 = d2 = D) turning about its opening angle [-]."""
    a = np.radians(alpha_deg)
    c, s = np.cos(a), np.sin(a)
    return -c * (1.0 + 2.0 * c) / (2.0 * s * s)


def report(spec: str, alpha0: float, out: dict, p0: float) -> None:
    curve, orient, local = out["curve"], out["orient"], out["local"]
    print(f"\n== {spec} alpha0 = {alpha0:g} deg, phi_g = {math.degrees(math.atan(out['cell'].mu)):g} deg, {orient.n_cells} cells")
    for eps in (0.005, 0.01, 0.02, 0.05, 0.10, 0.15):
        k = np.argmin(np.abs(curve[:, 0] - eps))
        if abs(curve[k, 0] - eps) < 1e-9 + 0.5 * (curve[1, 0] - curve[0, 0]):
            print(f"  eps_a = {eps:5.3f}: p/p0 = {curve[k, 1]:.3f}")
    print(f"  lowest p/p0 = {curve[:, 1].min():.3f} at eps_a = {curve[np.argmin(curve[:, 1]), 0]:.3f}")
    cell = out["cell"]
    # per plane: its in-plane area strain on the path (per unit axial strain) and whether its axis is compressed
    area = np.concatenate([local[:, 0] + local[:, 1], local[:, 0] + local[:, 2]]) / local[:, 0].max()
    closing = np.concatenate([local[:, 0], local[:, 0]]) < 0.0
    classes = {"compressed planes (area strain > +0.1)": area > 0.1,
               "isochoric planes (|area strain| <= 0.1)": np.abs(area) <= 0.1,
               "extended planes (area strain < -0.1)": area < -0.1}
    weight = np.concatenate([orient.weights, orient.weights])
    for eps, (state, moment, volume) in sorted(out["snaps"].items()):
        planes = [cell.plane_response(state.a)[0], cell.plane_response(state.b)[0]]
        p_plane = weight * np.concatenate([m[:, 0, 0] + m[:, 1, 1] for m in planes]) / (3.0 * volume * p0)
        alpha = np.degrees(np.concatenate([state.a.alpha, state.b.alpha]))
        loaded = np.concatenate([state.a.N1, state.b.N1]) > 0.0
        print(f"  eps_a = {eps:.2f}: p/p0 = {p_plane.sum():.3f}")
        for name, m in classes.items():
            for tag, sel in (("axis compressed", m & ~closing), ("axis extended", m & closing)):
                if sel.any():
                    print(f"      {name}, {tag}: {weight[sel].sum() / 2:.0%} of planes carry p/p0 = "
                          f"{p_plane[sel].sum():.3f}; alpha {alpha[sel].min():.1f}-{alpha[sel].max():.1f} deg "
                          f"(median {np.median(alpha[sel]):.1f}); contact 1-2 closed in {loaded[sel].mean():.0%}")


def plane_strains(out: dict) -> None:
    """Per-plane strain ratios on the isochoric path."""
    local, orient = out["local"], out["orient"]
    d = local[0].sum() * 0 + 1.0
    inc = local / np.abs(local).max()
    n, t1, t2 = inc[:, 0], inc[:, 1], inc[:, 2]
    area_a, area_b = n + t1, n + t2
    area = np.concatenate([area_a, area_b])
    w = np.concatenate([orient.weights, orient.weights]) / 2
    print("\n== planes of the ten-sphere cell on the isochoric triaxial path (d_eps_1 = 1)")
    print(f"  plane area strain d_eps_n + d_eps_t: min {area.min():+.3f}, max {area.max():+.3f}, "
          f"weighted mean {w @ area:+.4f}; compressed planes {w[area > 1e-9].sum():.0%}, "
          f"extended {w[area < -1e-9].sum():.0%} (2D: every cell 0)")
    axial = np.argmax(np.abs(orient.frames[:, 0, 0]))
    print(f"  cell with axis nearest e1 (n.e1 = {orient.frames[axial, 0, 0]:+.3f}): d_eps_n = {n[axial]:+.3f}, "
          f"d_eps_t1 = {t1[axial]:+.3f}, d_eps_t2 = {t2[axial]:+.3f}, ratio r = {t1[axial] / n[axial]:+.3f} (2D: -1)")
    print(f"  cell volume strain d_eps_n + d_eps_t1 + d_eps_t2: max abs {np.abs(n + t1 + t2).max():.1e}")
    for a in (50, 53.6, 55, 60, 64.3, 65, 75, 85):
        print(f"  rigid planar cell alpha = {a:5.1f} deg: r_mech = {mechanism_ratio(np.array(a)):+.3f}")


AXIS_BINS = (0.0, 0.3, 0.5, 0.577, 0.7, 0.85, 1.0001)
"""Edges of the groups of |n.e1| in ``by_axis`` (0.577: the cone where the axisymmetric deviator vanishes)."""


def by_axis(out: dict, p0: float) -> None:
    """p/p0 carried by the cells grouped by |n.e1| of their axis, with their plane-A opening angles, the share
    with contact 1-2 closed and the mean T1/N1 of those, at the probes 5 and 15 %."""
    orient, cell, local = out["orient"], out["cell"], out["local"]
    cosine = np.abs(orient.frames[:, 0, 0])
    print(f"  by |n.e1| (weight; d_eps_n per unit axial increment):")
    for eps, (state, moment, volume) in sorted(out["snaps"].items()):
        if eps not in (0.05, 0.15):
            continue
        share = orient.weights * np.trace(moment, axis1=1, axis2=2) / (3.0 * volume * p0)
        alpha = np.degrees(state.a.alpha)
        closed = state.a.N1 > 0.0
        ratio = np.where(closed, np.abs(state.a.T1) / np.where(closed, state.a.N1, 1.0), 0.0)
        print(f"  eps_a = {eps:.2f}: p/p0 = {share.sum():.3f}")
        for lo, hi in zip(AXIS_BINS[:-1], AXIS_BINS[1:]):
            sel = (cosine >= lo) & (cosine < hi)
            if not sel.any():
                continue
            print(f"    |n.e1| {lo:.3f}-{min(hi, 1.0):.3f} (weight {orient.weights[sel].sum():.2f}, d_eps_n "
                  f"{local[sel, 0].mean() / out['increment']:+.2f}): p/p0 {share[sel].sum():.3f}, alpha "
                  f"{alpha[sel].min():.1f}-{alpha[sel].max():.1f} deg, contact 1-2 closed in {closed[sel].mean():.0%}, "
                  f"T1/N1 {ratio[sel].mean():.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--alpha0", default="55,65,75")
    parser.add_argument("--kind", default="hcell3d")
    parser.add_argument("--order", type=int, default=11)
    parser.add_argument("--spins", type=int, default=4)
    parser.add_argument("--p0", type=float, default=2e5)
    parser.add_argument("--increment", type=float, default=1e-3)
    parser.add_argument("--eps-max", type=float, default=0.15)
    parser.add_argument("--phi-g", type=float, default=ContactLaw.phi_g_deg, help="inter-granular friction angle [deg]")
    parser.add_argument("--by-axis", action="store_true", help="the cells grouped by |n.e1| at 5 and 15 %%")
    parser.add_argument("--gain", type=float, default=None,
                        help="gain on the cell deviator of an axisymmetric kind (default: the kind's own)")
    args = parser.parse_args()
    if args.gain is not None:
        orientation_module.AXISYMMETRIC_MAP = orientation_module.axisymmetric_map(args.gain)
    first = True
    for spec in args.kind.split(","):
        for alpha0 in (float(a) for a in args.alpha0.split(",")):
            out = run_path(spec, alpha0, order=args.order, spins=args.spins, p0=args.p0,
                           increment=args.increment, eps_max=args.eps_max, phi_g_deg=args.phi_g)
            if first:
                plane_strains(out)
                first = False
            report(spec, alpha0, out, args.p0)
            if args.by_axis:
                by_axis(out, args.p0)


if __name__ == "__main__":
    main()
