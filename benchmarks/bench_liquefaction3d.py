"""Run: python benchmarks/bench_liquefaction3d.py [--quick] [--order 23] [--increment 1e-3]

Static liquefaction and strength under a lateral deviator of the 3D cells, closed form, p0 = 2e5 Pa
(2D: 2e5 N/m), against the 2D H-cell. Prints and writes ``benchmarks/results/liquefaction3d.txt``
(``--quick``: ``liquefaction3d_quick.txt``; other orders or sections:
``liquefaction3d_order{N}_sections{K}.txt``):

1. Undrained compression to eps_a = 15 % (triaxial; 2D: constant-volume biaxial) over alpha0: the
   lowest p/p0, p/p0 at the end and the peak q/p0, for ``hcell3d-sand`` (kinematics "amplified"),
   ``hcell3d-axisym``, the projected ``hcell3d`` and the 2D ``hcell``; then the liquefying window
   (lowest p/p0 < 0.3 by 15 %), its edges found by bisection to 0.02 deg.
2. The window against the gain g on the cell deviator (``orientation.axisymmetric_map``; g = 1 is
   ``hcell3d-axisym``, g = 2 ``hcell3d-sand``).
3. True triaxial compression at p = p0 (``--true B``; b = 0 is ``--constant-p``) to 15 %: peak q/p0
   for b = 0, 0.25, 0.5, 0.75, 1 against the Matsuoka-Nakai criterion through the b = 0 peak
   (``matsuoka_nakai_q``), dense and loose states.
4. Drained compression (sigma2 = sigma3 = p0) of the dense and loose states: eps_v at 15 %.
5. DEM against the closed form, undrained, dense and loose, largest |dp| and |dq| over p0 up to the
   first increment with a cell whose lateral grains of the two planes meet (``n_cross_plane``), where
   the closed form stops holding (the DEM models that contact), and to 15 %; also at two liquefying
   states (``DEM_STATES``).
6. The same at ``DEM_GAIN`` (``hcell3d-axisym``'s map with that gain) at ``DEM_STATES``.
7. The DEM's window against the gain (``WINDOW_GAINS``), for the cell as built (the lateral grains of
   the two planes meet and jam, as in YADE: tests/data/yade3d_sand) and for the cell without the 16
   candidate pairs between them (``decoupled``, the closed form's hypothesis), with the largest |dp|,
   |dq| over p0 of the decoupled DEM against the closed form at ``DEM_STATES`` and the dense state.
8. The 3D void-ratio map's range (``density.OPENING_RANGE_DEG[3]``), DEM and closed form in one run each
   (``hmodel triaxial --backend analytical,dem``): the window's loose edge in ``EDGE_STEP_DEG`` steps and
   bisected to 0.01 deg, also at a tenth of the increment; undrained compression over the map's angles
   (lowest and end p/p0, the map's e0), every ``EDGE_STEP_DEG`` within its loose third, whether the whole
   loose third liquefies; drained eps_v of the map's dense and loose ends.

Sections 1-6 run through ``hmodel triaxial`` / ``hmodel biaxial`` in this process (section 7 calls the
element-test driver, as the decoupled cell has no spec) (``--spins 1``: the
response of the axisymmetric and amplified cells does not depend on the spin; the projected cell gets
``--spins 4``). Signs: compression positive; eps_v > 0 is contraction.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import datetime
import io
import math
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
from scipy.optimize import brentq

from homogenization.backends import make_cell_model
from homogenization.cli import hmodel
from homogenization.element_test import driver, programme as programmes
from homogenization.material import orientation
from homogenization.material.density import OPENING_RANGE_DEG, default_map
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.mesostructure import Mesostructure

HERE = Path(__file__).resolve().parent
P0 = 2e5
"""Confining pressure [Pa] (2D: [N/m])."""
EPS_MAX = 0.15
"""Axial strain at the end of the shear stage [-]."""
LIQUEFIED = 0.3
"""A test liquefies where the lowest p/p0 falls below this [-]."""
B_VALUES = (0.0, 0.25, 0.5, 0.75, 1.0)
GAINS = (1.0, 1.58, 2.0, 2.5, 3.0, 3.5)
DEM_STATES = (52.0, 55.0)
"""Liquefying states where the DEM is also run (section 5), besides the dense and loose ones [deg]."""
DEM_GAIN = 3.5
"""A gain whose closed-form window passes 5 deg, run with the DEM at DEM_STATES (section 6)."""
WINDOW_GAINS = (2.0, 3.0, 3.5)
"""Gains of the DEM windows (section 7)."""
EDGE_SCAN_DEG = (55.2, 56.0)
"""Opening angles [deg] between which section 8 looks for the window's loose edge."""
EDGE_STEP_DEG = 0.1
"""Step [deg] of section 8's edge scan and of its rows within the map's loose third."""


RETRIES: list[str] = []
"""Runs whose stress control failed at the asked increment and were rerun at a smaller one (reported)."""


def run(command: str, spec: str, alpha0: float, test: list[str], *, order: int, spins: int, increment: float,
        backends: str = "analytical") -> dict[str, np.ndarray]:
    """One ``hmodel`` run; returns the shear-stage columns of curve.csv (one dict per backend if several).
    Where the stress control fails (singular tangent), reruns at half the increment, twice at most,
    and records it in ``RETRIES``."""
    for attempt in range(3):
        try:
            return _run(command, spec, alpha0, test, order=order, spins=spins, increment=increment / 2**attempt,
                        backends=backends)
        except RuntimeError as exc:
            if attempt == 2:
                raise SystemExit(str(exc)) from None
            RETRIES.append(f"{spec}:alpha0={alpha0:g} {' '.join(test)} at increment {increment / 2**attempt:g}: {exc}")
    raise AssertionError("unreachable")


def _run(command: str, spec: str, alpha0: float, test: list[str], *, order: int, spins: int, increment: float,
         backends: str) -> dict[str, np.ndarray]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        argv = [command, "--backend", backends, "--mesostructure", f"{spec}:alpha0={alpha0:g}", "--p0", f"{P0:g}",
                "--eps-max", f"{EPS_MAX:g}", "--increment", f"{increment:g}", "--out", str(out), *test]
        argv += ["--order", str(order), "--spins", str(spins)] if command == "triaxial" else ["--orientations", "90"]
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
            code = hmodel.main(argv)
        if code:
            raise RuntimeError((err.getvalue().strip().splitlines() or ["failed"])[-1])
        curves = {}
        for name in backends.split(","):
            path = out / name / "curve.csv" if "," in backends else out / "curve.csv"
            every = list(csv.DictReader(path.open()))
            rows = [r for r in every if r["stage"] != "iso"]
            curves[name] = {key: np.array([float(r[key]) for r in rows]) for key in rows[0] if key != "stage"}
            iso = [r for r in every if r["stage"] == "iso"][-1]
            if name == "analytical" and command == "triaxial":
                with h5py.File(path.parent / "run.h5") as run_file:
                    cross = np.asarray(run_file["diagnostics/n_cross_plane"])
                curves[name]["n_cross_plane"] = cross[-len(rows):]
            curves[name]["eps_v_iso"] = sum(float(iso[key]) for key in ("eps11", "eps22", "eps33") if key in iso)
    return curves if "," in backends else curves[backends]


def undrained(spec: str, alpha0: float, args, spins: int = 1) -> tuple[float, float, float]:
    """(lowest p/p0, end p/p0, peak q/p0) of the undrained test."""
    if spec == "hcell":
        curve = run("biaxial", spec, alpha0, [], order=args.order, spins=spins, increment=args.increment)
    else:
        curve = run("triaxial", spec, alpha0, ["--undrained"], order=args.order, spins=spins, increment=args.increment)
    return curve["p"].min() / P0, curve["p"][-1] / P0, curve["q"].max() / P0


def window(results: dict[float, float], probe) -> tuple[float, float] | None:
    """Edges of the alpha0 interval where lowest p/p0 < LIQUEFIED, bisected to 0.02 deg from the grid."""
    grid = sorted(results)
    inside = [a for a in grid if results[a] < LIQUEFIED]
    if not inside:
        return None
    edges = []
    for first, step in ((inside[0], -1), (inside[-1], +1)):
        k = grid.index(first)
        if not 0 <= k + step < len(grid):
            edges.append(float("nan"))
            continue
        lo, hi = first, grid[k + step]
        while abs(hi - lo) > 0.02:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if probe(mid) < LIQUEFIED else (lo, mid)
        edges.append(0.5 * (lo + hi))
    return edges[0], edges[1]


def matsuoka_nakai_q(q_compression: float, p: float, b: float) -> float:
    """q [same unit as p] at mean stress p and b = (s2 - s3)/(s1 - s3) on the Matsuoka-Nakai surface
    I1 I2 / I3 = const through the compression point (q_compression, p), b = 0."""
    def principal(delta: float, b: float) -> tuple[float, float, float]:
        s3 = p - delta * (1.0 + b) / 3.0
        return s3 + delta, s3 + b * delta, s3

    def mn(s: tuple[float, float, float]) -> float:
        s1, s2, s3 = s
        return (s1 + s2 + s3) * (s1 * s2 + s2 * s3 + s3 * s1) / (s1 * s2 * s3)

    target = mn(principal(q_compression, 0.0))
    delta_max = 3.0 * p / (1.0 + b) * (1.0 - 1e-12)
    delta = brentq(lambda d: mn(principal(d, b)) - target, 1e-12 * p, delta_max)
    return delta * math.sqrt(1.0 - b + b * b)


def gain_probe(gain: float, args):
    """lowest p/p0 of hcell3d-axisym driven with the deviator gain ``gain`` (the map swapped for the run)."""
    def probe(alpha0: float) -> float:
        saved = orientation.AXISYMMETRIC_MAP
        orientation.AXISYMMETRIC_MAP = orientation.axisymmetric_map(gain) if gain != 1.0 else saved
        try:
            return undrained("hcell3d-axisym", alpha0, args)[0]
        finally:
            orientation.AXISYMMETRIC_MAP = saved
    return probe


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="coarse grid, order 11, no gain scan")
    parser.add_argument("--order", type=int, default=23, help="Lebedev order of the cell axes (default 23)")
    parser.add_argument("--increment", type=float, default=1e-3, help="strain increment (default 1e-3)")
    parser.add_argument("--dense", type=float, default=49.0, help="dense alpha0 [deg] (default 49)")
    parser.add_argument("--loose", type=float, default=54.0, help="loose alpha0 [deg] (default 54)")
    parser.add_argument("--sections", default="1,2,3,4,5,6",
                        help="sections to run (default 1-6; 7: DEM windows; 8: the 3D void-ratio map's range)")
    args = parser.parse_args()
    sections = {int(k) for k in args.sections.split(",")}
    if args.quick:
        args.order = 11
    lines: list[str] = []

    def say(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    start = time.time()
    say(f"# bench_liquefaction3d {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; p0 = {P0:g}, "
        f"eps_a to {EPS_MAX:g}, increment {args.increment:g}, Lebedev order {args.order} (2D: 90 orientations)")
    if 1 in sections:
        undrained_section(args, say)
    if 2 in sections and not args.quick:
        say("\n## 2. Window against the gain g on the cell deviator (hcell3d-axisym's map with g)")
        for gain in GAINS:
            probe = gain_probe(gain, args)
            coarse = {a: probe(a) for a in np.arange(49.0, 60.01, 1.0)}
            edges = window(coarse, probe)
            text = "none" if edges is None else f"{edges[0]:.2f}-{edges[1]:.2f} deg, width {edges[1] - edges[0]:.2f} deg"
            say(f"  g = {gain:4.2f}: {text}")
    if 3 in sections:
        true_triaxial_section(args, say)
    if 4 in sections:
        drained_section(args, say)
    if 5 in sections:
        dem_section(args, say)
    if 6 in sections:
        dem_section(args, say, DEM_GAIN)
    if 7 in sections:
        dem_window_section(args, say)
    if 8 in sections:
        map_range_section(args, say)
    say(f"\nReruns at a smaller increment (stress control failed): {len(RETRIES)}")
    for line in RETRIES:
        say(f"  {line}")
    say(f"\n# {time.time() - start:.0f} s")
    name = "liquefaction3d_quick.txt" if args.quick else "liquefaction3d.txt"
    if sections != {1, 2, 3, 4, 5, 6} or args.order != 23:
        name = f"liquefaction3d_order{args.order}_sections{''.join(str(k) for k in sorted(sections))}.txt"
    (HERE / "results" / name).write_text("\n".join(lines) + "\n")


def undrained_section(args, say) -> None:
    grid = np.arange(47.0, 62.01, 1.0 if args.quick else 0.5)
    cells = [("hcell3d-sand", 1), ("hcell3d-axisym", 1), ("hcell", 1), ("hcell3d", 4)]
    say("\n## 1. Undrained compression: lowest p/p0, end p/p0, peak q/p0")
    say("alpha0 | " + " | ".join(f"{spec} (min, end, q)" for spec, _ in cells))
    table: dict[str, dict[float, float]] = {spec: {} for spec, _ in cells}
    projected_grid = set(grid[::6] if not args.quick else grid[::4])
    for alpha0 in grid:
        row = []
        for spec, spins in cells:
            if spec == "hcell3d" and alpha0 not in projected_grid:
                row.append("")
                continue
            low, end, q = undrained(spec, alpha0, args, spins)
            table[spec][alpha0] = low
            row.append(f"{low:.3f}, {end:.3f}, {q:.3f}")
        say(f"{alpha0:5.1f} | " + " | ".join(row))
    say(f"\nWindow (lowest p/p0 < {LIQUEFIED} by {EPS_MAX:g}):")
    for spec, spins in cells:
        edges = window(table[spec], lambda a, spec=spec, spins=spins: undrained(spec, a, args, spins)[0])
        text = "none" if edges is None else f"{edges[0]:.2f}-{edges[1]:.2f} deg, width {edges[1] - edges[0]:.2f} deg"
        say(f"  {spec}: {text}")


def true_triaxial_section(args, say) -> None:
    say("\n## 3. True triaxial at p = p0: peak q/p0 against Matsuoka-Nakai through the b = 0 peak")
    for spec in ("hcell3d-sand", "hcell3d-axisym"):
        for alpha0 in (args.dense, args.loose):
            peaks = []
            for b in B_VALUES:
                test = ["--constant-p"] if b == 0.0 else ["--true", f"{b:g}"]
                curve = run("triaxial", spec, alpha0, test, order=args.order, spins=1, increment=args.increment)
                peaks.append(curve["q"].max() / P0)
            cells_text = []
            for b, peak in zip(B_VALUES, peaks):
                mn = matsuoka_nakai_q(peaks[0], 1.0, b)
                cells_text.append(f"b={b:g}: {peak:.3f} (MN {mn:.3f}, ratio {peak / mn:.2f})")
            say(f"  {spec} alpha0 = {alpha0:g}: " + "; ".join(cells_text))


def drained_section(args, say) -> None:
    say("\n## 4. Drained compression (sigma2 = sigma3 = p0): eps_v of the shear stage at 15 % (> 0 contraction)")
    for spec in ("hcell3d-sand", "hcell3d-axisym"):
        for alpha0 in (args.dense, args.loose):
            curve = run("triaxial", spec, alpha0, ["--drained"], order=args.order, spins=1, increment=args.increment)
            eps_v = curve["eps11"] + curve["eps22"] + curve["eps33"] - curve["eps_v_iso"]
            say(f"  {spec} alpha0 = {alpha0:g}: eps_v {eps_v[-1]:+.4f} (lowest {eps_v.min():+.4f}), "
                f"peak q/p0 {curve['q'].max() / P0:.3f}, end q/p0 {curve['q'][-1] / P0:.3f}")


def dem_section(args, say, gain: float | None = None) -> None:
    states = (args.dense, *DEM_STATES[:1], args.loose, *DEM_STATES[1:]) if gain is None else DEM_STATES
    spec = "hcell3d-sand" if gain is None else "hcell3d-axisym"
    title = "5. DEM against the closed form, undrained, hcell3d-sand" if gain is None else \
        f"6. DEM against the closed form, undrained, gain g = {gain:g}"
    say(f"\n## {title}: largest |dp|/p0, |dq|/p0 while no planes meet (closed form valid), and to 15 %")
    saved = orientation.AXISYMMETRIC_MAP
    for alpha0 in states:
        if gain is not None:
            orientation.AXISYMMETRIC_MAP = orientation.axisymmetric_map(gain)
        try:
            curves = run("triaxial", spec, alpha0, ["--undrained"], order=args.order, spins=1,
                         increment=args.increment, backends="analytical,dem")
        finally:
            orientation.AXISYMMETRIC_MAP = saved
        a, d = curves["analytical"], curves["dem"]
        dp, dq = np.abs(a["p"] - d["p"]) / P0, np.abs(a["q"] - d["q"]) / P0
        met = a["n_cross_plane"] > 0
        valid = np.cumsum(met) == 0
        meet = f"planes first meet at eps_a = {a['eps11'][np.argmax(met)]:.4f} ({a['n_cross_plane'].max():.0f} cells " \
               f"at most)" if met.any() else "planes never meet"
        say(f"  alpha0 = {alpha0:g}: {meet}; before: |dp| {dp[valid].max():.1e}, |dq| {dq[valid].max():.1e}; "
            f"to 15 %: |dp| {dp.max():.1e}, |dq| {dq.max():.1e}; p/p0 at 15 % {a['p'][-1] / P0:.3f} (closed form), "
            f"{d['p'][-1] / P0:.3f} (DEM); lowest {a['p'].min() / P0:.3f}, {d['p'].min() / P0:.3f}")


def decoupled(meso: Mesostructure) -> Mesostructure:
    """The ten-sphere cell ``meso`` without the candidate pairs between a lateral grain of plane A (2, 3,
    5, 6) and one of plane B (7-10)."""
    keep = np.array([not (i in (1, 2, 4, 5) and j in (6, 7, 8, 9)) for i, j in meso.pairs])
    return dataclasses.replace(meso, pairs=meso.pairs[keep], pair_label=meso.pair_label[keep])


def driven_undrained(backend: str, alpha0: float, gain: float, apart: bool, args) -> driver.Record:
    """Undrained triaxial run of the ten-sphere cell with the amplified map of ``gain`` (``apart``: decoupled)."""
    meso = resolve_mesostructure(f"hcell3d-axisym:alpha0={alpha0:.6f}")
    saved = orientation.AXISYMMETRIC_MAP
    orientation.AXISYMMETRIC_MAP = orientation.axisymmetric_map(gain)
    try:
        programme = programmes.triaxial(P0, EPS_MAX, args.increment, test="undrained", iso_increment=1e-4)
        return driver.run(make_cell_model(backend, dim=3), programme, mesostructure=decoupled(meso) if apart else meso,
                          lebedev_order=args.order, n_spins=1, progress=False)
    finally:
        orientation.AXISYMMETRIC_MAP = saved


def dem_window_section(args, say) -> None:
    say("\n## 7. The DEM's window against the gain: the cell as built (its planes meet and jam) and decoupled")
    for gain in WINDOW_GAINS:
        for apart in (False, True):
            def probe(alpha0: float, gain=gain, apart=apart) -> float:
                record = driven_undrained("dem", alpha0, gain, apart, args)
                return float(record.p[record.stage == "shear"].min() / P0)
            coarse = {a: probe(a) for a in np.arange(49.0, 58.01, 0.5)}
            edges = window(coarse, probe)
            text = "none" if edges is None else f"{edges[0]:.2f}-{edges[1]:.2f} deg, width {edges[1] - edges[0]:.2f} deg"
            say(f"  g = {gain:4.2f}, {'decoupled' if apart else 'as built '}: {text}")
        for alpha0 in (args.dense, *DEM_STATES):
            dem, closed = (driven_undrained(b, alpha0, gain, b == "dem", args) for b in ("dem", "analytical"))
            shear = closed.stage == "shear"
            dp, dq = (np.abs(getattr(dem, k) - getattr(closed, k))[shear].max() / P0 for k in ("p", "q"))
            say(f"    decoupled DEM vs closed form, alpha0 = {alpha0:g}: |dp| {dp:.1e}, |dq| {dq:.1e}; lowest p/p0 "
                f"{dem.p[shear].min() / P0:.3f} (closed form {closed.p[shear].min() / P0:.3f}), at 15 % "
                f"{dem.p[shear][-1] / P0:.3f} ({closed.p[shear][-1] / P0:.3f}); closed-form cells whose planes meet: "
                f"{np.max(closed.diagnostics['n_cross_plane']):.0f}")


def both_undrained(alpha0: float, args, increment: float | None = None) -> dict[str, dict[str, np.ndarray]]:
    """The undrained test of ``hcell3d-sand`` at ``alpha0``, by backend ("analytical", "dem"): ``run``'s columns."""
    return run("triaxial", "hcell3d-sand", alpha0, ["--undrained"], order=args.order, spins=1,
               increment=args.increment if increment is None else increment, backends="analytical,dem")


def lowest_p(alpha0: float, args, increment: float) -> dict[str, float]:
    """Lowest p/p0 of the undrained test by backend."""
    return {name: float(curve["p"].min() / P0) for name, curve in both_undrained(alpha0, args, increment).items()}


def loose_edge(args, increment: float, say) -> None:
    """The window's loose edge per backend: lowest p/p0 every EDGE_STEP_DEG over EDGE_SCAN_DEG, then bisected to
    0.01 deg between the last liquefying and the first non-liquefying angle."""
    grid = np.round(np.arange(EDGE_SCAN_DEG[0], EDGE_SCAN_DEG[1] + 1e-9, EDGE_STEP_DEG), 6)
    lowest = {a: lowest_p(float(a), args, increment) for a in grid}
    say(f"  increment {increment:g}: lowest p/p0 closed form / DEM: " + "; ".join(
        f"{a:.1f}: {r['analytical']:.4f} / {r['dem']:.4f}" for a, r in lowest.items()))
    for name in ("analytical", "dem"):
        inside = [a for a in grid if lowest[a][name] < LIQUEFIED]
        if not inside or inside[-1] == grid[-1]:
            say(f"    {name}: no edge within {EDGE_SCAN_DEG[0]:g}-{EDGE_SCAN_DEG[1]:g} deg")
            continue
        lo, hi = inside[-1], grid[list(grid).index(inside[-1]) + 1]
        while hi - lo > 0.01 + 1e-9:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if lowest_p(mid, args, increment)[name] < LIQUEFIED else (lo, mid)
        say(f"    {name}: loose edge {lo:.3f}-{hi:.3f} deg")


def map_range_section(args, say) -> None:
    dense, loose = OPENING_RANGE_DEG[3]
    third = loose - (loose - dense) / 3.0
    density = default_map(3)
    say(f"\n## 8. The 3D void-ratio map's range (OPENING_RANGE_DEG[3] = {dense:g}-{loose:g} deg, loose third "
        f"{third:.2f}-{loose:g} deg), hcell3d-sand, DEM and closed form")
    say(f"The window's loose edge (lowest p/p0 < {LIQUEFIED} by {EPS_MAX:g}):")
    for increment in (args.increment, args.increment / 10.0):
        loose_edge(args, increment, say)
    coarse = np.arange(dense, third, 0.5)
    fine = np.arange(loose, third, -EDGE_STEP_DEG)[::-1]
    grid = np.round(np.unique(np.concatenate([coarse, [third], fine])), 6)
    say(f"Undrained over the map (e0: default_map(3), e_min {density.e_min:g}, e_max {density.e_max:g}):")
    say("alpha0  e0     third | closed form: lowest p/p0, end p/p0 | DEM: lowest p/p0, end p/p0 | max |dp|/p0 | "
        "planes meet from eps_a")
    worst = {"analytical": 0.0, "dem": 0.0}
    for alpha0 in grid:
        curves = both_undrained(float(alpha0), args)
        p = {name: curve["p"] / P0 for name, curve in curves.items()}
        a, d = p["analytical"], p["dem"]
        met = curves["analytical"]["n_cross_plane"] > 0
        meet = f"{curves['analytical']['eps11'][np.argmax(met)]:.4f}" if met.any() else "never"
        in_third = alpha0 >= third - 1e-6  # the grid is rounded to 1e-6 deg
        if in_third:
            worst = {k: max(worst[k], p[k].min()) for k in worst}
        say(f"{alpha0:6.2f}  {density.void_ratio(alpha0):.3f}  {'yes' if in_third else 'no ':<5} | {a.min():.4f}, "
            f"{a[-1]:.4f} | {d.min():.4f}, {d[-1]:.4f} | {np.abs(a - d).max():.1e} | {meet}")
    say(f"Loose third liquefies at every row (largest lowest p/p0 there: closed form {worst['analytical']:.4f}, DEM "
        f"{worst['dem']:.4f}, < {LIQUEFIED}): {max(worst.values()) < LIQUEFIED}")
    say("Drained compression (sigma2 = sigma3 = p0), eps_v of the shear stage at 15 % (> 0 contraction), closed form / DEM:")
    for alpha0 in (dense, loose):
        curves = run("triaxial", "hcell3d-sand", alpha0, ["--drained"], order=args.order, spins=1,
                     increment=args.increment, backends="analytical,dem")
        eps_v = {k: c["eps11"] + c["eps22"] + c["eps33"] - c["eps_v_iso"] for k, c in curves.items()}
        met = curves["analytical"]["n_cross_plane"] > 0
        k = int(np.argmax(met)) if met.any() else -1
        meet = f"planes meet from eps_a = {curves['analytical']['eps11'][k]:.4f}, eps_v there " \
               f"{eps_v['analytical'][k]:+.4f} / {eps_v['dem'][k]:+.4f}" if met.any() else "planes never meet"
        say(f"  alpha0 = {alpha0:g}: eps_v {eps_v['analytical'][-1]:+.4f} / {eps_v['dem'][-1]:+.4f} (lowest "
            f"{eps_v['analytical'].min():+.4f} / {eps_v['dem'].min():+.4f}); {meet}")


if __name__ == "__main__":
    sys.exit(main())
