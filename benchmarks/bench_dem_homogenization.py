"""python benchmarks/bench_dem_homogenization.py [--orientations 360] [--increment 5e-4] [--iso-increment 1e-3] [--sweep 1e-4,2e-4,5e-4,1e-3,2e-3]

Issue-4 acceptance: the meso-DEM homogenisation reproduces the analytical H-model. Runs the
three constant-volume cases (alpha0 = 55 deg at p0 = 5.85e6 and 2e5 N/m, alpha0 = 40 deg at
5.85e6 N/m; isotropic stage to p0, then shear to eps1 = --eps-max) with the analytical and
the DEM backends on the same programme, and prints per case:

- wall times of the analytical and the DEM run (and of the analytical run at the converged
  increments of docs/model.md, "Reference response", 1e-5 / 5e-6);
- max |p_dem - p_ana| / p0 and max |q_dem - q_ana| / p0 over every increment (same programme)
  and against the converged analytical run (interpolated at the DEM's eps1): the second
  measures what the macro increment itself costs, the same for both backends;
- DEM substeps per cell and increment in the shear stage (mean, max), of which those beyond
  the n_drive = ceil(|d_eps| / strain_per_substep) driving substeps at the coarse rate
  (relaxation, and driving at the refined rate of the adaptive stepping), unconverged
  cell-increments, the relative error of p after the isotropic stage,
  p/p0 and q/p0 at eps1 = 10 %, next to the reference table.

Writes benchmarks/results/dem_homogenization.json and docs/figures/dem_vs_analytical_<case>.png
(the two backends overlaid in the 2x2 figure). ``--sweep`` instead runs the DEM at several
shear increments (the isotropic one fixed) and prints and stores the same numbers per
increment, to choose the cheapest increment that keeps the 1 % agreement. Timings come with
the load average: the machine may be shared. Sign convention: compression positive.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.material import orientation
from homogenization.output import figures
from homogenization.output.figure_style import number
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import DemSettings
from warp_hcell.core.provenance import git_revision

ROOT = Path(__file__).resolve().parent.parent
CASES = {"a55_p5.85e6": (55.0, 5.85e6), "a55_p2e5": (55.0, 2e5), "a40_p5.85e6": (40.0, 5.85e6)}
"""Acceptance cases: name -> (alpha0 [deg], p0 [N/m])."""
REFERENCE_P10 = {"a55_p5.85e6": (0.766, 0.386), "a55_p2e5": (0.191, 0.051), "a40_p5.85e6": (1.037, 0.945)}
"""p/p0 and q/p0 at eps1 = 10 % from docs/model.md, "Reference response" (independent implementation, N = 360)."""
CONVERGED = (1e-5, 5e-6)
"""Shear and isotropic increments of the reference table (converged analytical run)."""


def shear_part(record: driver.Record) -> tuple[np.ndarray, np.ndarray]:
    """(mask of the shear increments, eps1 counted from the end of the isotropic stage)."""
    shear = record.stage == "shear"
    eps_iso = record.eps11[record.stage == "iso"][-1]
    return shear, record.eps11[shear] - eps_iso


def driving_substeps(n_orientations: int, increment: float, settings: DemSettings) -> np.ndarray:
    """Substeps per cell that only drive the cell (n_drive) in one shear increment, shape (N,)."""
    d_local = orientation.localise(orientation.orientations(n_orientations), np.array([increment, -increment, 0.0]))
    return np.ceil(np.abs(d_local).max(axis=1) / settings.strain_per_substep)


def timed_run(model, programme, alpha0_deg: float, n_orientations: int) -> tuple[driver.Record, float, float]:
    """The record, its wall time [s] and the CPU time of this process (all threads) [s]."""
    start, cpu = time.perf_counter(), time.process_time()
    record = driver.run(model, programme, mesostructure=h_cell(alpha0_deg), n_orientations=n_orientations, progress=False)
    return record, time.perf_counter() - start, time.process_time() - cpu


def compare(name: str, args: argparse.Namespace, increment: float, analytical, dem,
            converged: driver.Record | None) -> tuple[dict, dict[str, driver.Record]]:
    """Run one case with both backends at ``increment``; the numbers of the acceptance table."""
    alpha0, p0 = CASES[name]
    programme = programmes.biaxial(p0, args.eps_max, increment, iso_increment=args.iso_increment)
    ana, t_ana, _ = timed_run(analytical, programme, alpha0, args.orientations)
    dem_record, t_dem, cpu_dem = timed_run(dem, programme, alpha0, args.orientations)
    shear, eps1 = shear_part(dem_record)
    per_cell = dem_record.diagnostics["substeps"][shear] / args.orientations
    drive = driving_substeps(args.orientations, increment, dem.settings).mean()
    iso_end = int(np.flatnonzero(dem_record.stage == "iso")[-1])
    row = {
        "case": name, "alpha0_deg": alpha0, "p0": p0, "n_orientations": args.orientations,
        "increment": increment, "iso_increment": args.iso_increment, "eps_max": args.eps_max,
        "n_increments": dem_record.n_increments,
        "time_analytical_s": t_ana, "time_dem_s": t_dem, "cpu_time_dem_s": cpu_dem,
        "time_dem_iso_s": float(dem_record.step_seconds[0]), "time_dem_shear_s": float(dem_record.step_seconds[1]),
        "max_dp_over_p0": float(np.abs(dem_record.p - ana.p).max() / p0),
        "max_dq_over_p0": float(np.abs(dem_record.q - ana.q).max() / p0),
        "substeps_per_cell_increment_mean": float(per_cell.mean()),
        "substeps_per_cell_increment_max": float(dem_record.diagnostics["max_substeps"][shear].max()),
        "relaxation_substeps_per_cell_increment_mean": float(per_cell.mean() - drive),
        "substeps_total": float(dem_record.diagnostics["substeps"].sum()),
        "unconverged_total": float(dem_record.diagnostics["n_unconverged"].sum()),
        "iso_p_relative_error": float(dem_record.p[iso_end] / p0 - 1.0),
        "eps_iso": float(dem_record.eps11[iso_end]),
        "p_over_p0_at_10pct": float(np.interp(0.1, eps1, dem_record.p[shear]) / p0),
        "q_over_p0_at_10pct": float(np.interp(0.1, eps1, dem_record.q[shear]) / p0),
        "reference_p_q_over_p0_at_10pct": REFERENCE_P10[name],
    }
    if converged is not None:
        c_shear, c_eps1 = shear_part(converged)
        row["max_dp_vs_converged_over_p0"] = float(
            np.abs(np.interp(eps1, c_eps1, converged.p[c_shear]) - dem_record.p[shear]).max() / p0)
        row["max_dq_vs_converged_over_p0"] = float(
            np.abs(np.interp(eps1, c_eps1, converged.q[c_shear]) - dem_record.q[shear]).max() / p0)
    return row, {"analytical": ana, "dem": dem_record}


def print_row(row: dict) -> None:
    conv = (f" | vs converged: dp {row['max_dp_vs_converged_over_p0']:.2e} dq {row['max_dq_vs_converged_over_p0']:.2e}"
            if "max_dp_vs_converged_over_p0" in row else "")
    ref_p, ref_q = row["reference_p_q_over_p0_at_10pct"]
    print(f"{row['case']:<12} inc {row['increment']:.0e}: analytical {row['time_analytical_s']:6.2f} s, "
          f"dem {row['time_dem_s']:6.1f} s (iso {row['time_dem_iso_s']:.1f} + shear {row['time_dem_shear_s']:.1f}; "
          f"CPU {row['cpu_time_dem_s']:.1f} s) | "
          f"max|dp|/p0 {row['max_dp_over_p0']:.2e} max|dq|/p0 {row['max_dq_over_p0']:.2e}{conv} | "
          f"substeps/cell/incr mean {row['substeps_per_cell_increment_mean']:.0f} "
          f"(relaxation {row['relaxation_substeps_per_cell_increment_mean']:.1f}) max {row['substeps_per_cell_increment_max']:.0f} | "
          f"unconverged {row['unconverged_total']:.0f} | p0 error {row['iso_p_relative_error']:.1e} | "
          f"p/p0, q/p0 at 10 %: {row['p_over_p0_at_10pct']:.3f}, {row['q_over_p0_at_10pct']:.3f} "
          f"(reference {ref_p}, {ref_q})", flush=True)


def machine() -> dict:
    load = os.getloadavg()
    return {"date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"), "cpus": os.cpu_count(),
            "load_average_1_5_15": [round(v, 2) for v in load], "git_revision": git_revision()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--orientations", type=int, default=360)
    parser.add_argument("--increment", type=float, default=5e-4, help="shear increment d_eps11 = -d_eps22 [-]")
    parser.add_argument("--iso-increment", type=float, default=1e-3, help="isotropic strain increment per component [-]")
    parser.add_argument("--eps-max", type=float, default=0.2)
    parser.add_argument("--threads", type=int, default=2, help="CPU threads of the DEM")
    parser.add_argument("--strain-per-substep", type=float, default=DemSettings.strain_per_substep,
                        help="DEM largest cell strain per substep [-] (the refined rate is capped to it)")
    parser.add_argument("--device", default="cpu", help="Warp device of the DEM")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    parser.add_argument("--sweep", default=None, help="comma list of shear increments: DEM cost and agreement per increment")
    parser.add_argument("--no-converged", action="store_true", help="skip the analytical run at 1e-5 / 5e-6")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "dem_homogenization.json")
    parser.add_argument("--figures", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args()
    cases = [c.strip() for c in args.cases.split(",")]
    for name in cases:
        if name not in CASES:
            parser.error(f"unknown case {name!r}; choose from {', '.join(CASES)}")

    analytical = make_cell_model("analytical")
    dem = make_cell_model("dem", device=args.device, threads=args.threads,
                          settings=DemSettings(strain_per_substep=args.strain_per_substep,
                                               refined_strain_per_substep=min(
                                                   args.strain_per_substep, DemSettings.refined_strain_per_substep)))
    increments = [float(v) for v in args.sweep.split(",")] if args.sweep else [args.increment]
    info = machine()
    print(f"load average {info['load_average_1_5_15']} on {info['cpus']} cpus; DEM threads={args.threads} "
          f"device={args.device} strain_per_substep={dem.settings.strain_per_substep:g} "
          f"force_tolerance={dem.settings.force_tolerance:g}; N={args.orientations}", flush=True)
    rows = []
    for name in cases:
        alpha0, p0 = CASES[name]
        converged, t_conv = None, math.nan
        if not args.no_converged:
            converged, t_conv, _ = timed_run(analytical, programmes.biaxial(p0, args.eps_max, CONVERGED[0],
                                                                      iso_increment=CONVERGED[1]), alpha0, args.orientations)
            print(f"{name:<12} analytical at the converged increments {CONVERGED}: {t_conv:.2f} s", flush=True)
        for increment in increments:
            row, records = compare(name, args, increment, analytical, dem, converged)
            row["time_analytical_converged_s"] = t_conv
            print_row(row)
            rows.append(row)
            if not args.sweep:
                title = (f"constant-volume biaxial test, H-cell, $\\alpha_0$ = {alpha0:g}°, $p_0 = {number(p0)}$ N/m, "
                         f"$N$ = {args.orientations}, increment ${number(increment)}$")
                args.figures.mkdir(parents=True, exist_ok=True)
                figures.save_figure(figures.make_figure(records, title=title),
                                     args.figures / f"dem_vs_analytical_{name}.png")
    result = {"machine": {**info, "load_average_end": [round(v, 2) for v in os.getloadavg()]},
              "settings": {"increment": args.increment if not args.sweep else increments,
                           "iso_increment": args.iso_increment, "eps_max": args.eps_max, "threads": args.threads,
                           "device": args.device, "dem_settings": asdict(dem.settings)},
              "cases" if not args.sweep else "sweep": rows}
    path = args.json if not args.sweep else args.json.with_name(args.json.stem + "_sweep.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
