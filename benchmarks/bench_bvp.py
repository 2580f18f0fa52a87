"""python benchmarks/bench_bvp.py [--elements 32,64] [--orientations 72] [--shear-steps 100] [--dem-steps K] [--out FILE]

Speed of the finite-element biaxial specimen (``homogenization.fe.solver``) at scale, the
closed-form (analytical), meso-ANN and meso-DEM backends side by side in one run, on one mesh
(default 32 x 64 bilinear quadrilaterals, 2 x 2 Gauss points: 8 192 material points) with
--orientations cells per point: alpha0 = 40 deg, p0 = 2e5 N/m, 20 isotropic steps, then
--shear-steps steps of 1e-3 (through the peak at about 3.5 %). Every Newton iteration is one
batched material update of all points.

Per backend: load steps run, wall [s], Newton iterations per step (mean, max), material-point
updates/s, cell-steps/s and, for the DEM, cell-substeps/s (the DEM's ``substeps`` diagnostic).
``--dem-steps K`` (and ``--ann-steps``, ``--analytical-steps``) run only the first K load steps of that backend and
extrapolate the wall time to the whole programme from the mean time per step of the steps run
(labelled "extrapolated"; the shear steps cost more than the isotropic ones, so K should reach
into the shear stage). Prints the machine load before and after (shared machine).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.cli.bvp import element_counts
from homogenization.fe import solver as fe
from homogenization.material import orientation
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.mesostructures.hcell import h_cell

P0 = 2e5
ALPHA0 = 40.0
ISO_STEPS = 20
RTOL = {"analytical": 1e-8, "ann": 1e-8, "dem": 1e-5}
"""Newton tolerance per backend (the DEM's equilibrium tolerance bounds its attainable residual)."""


def run_backend(name: str, nx: int, ny: int, n_orientations: int, shear_steps: int, limit: int | None) -> dict:
    """One homogeneous run of backend ``name``, the first ``limit`` load steps (None: all)."""
    specimen = fe.BiaxialSpecimen(nx, ny, newton_rtol=RTOL[name])
    model = make_cell_model(name)
    material = HomogenisedMaterial(model, orientation.orientations(n_orientations), h_cell(ALPHA0), specimen.n_points)
    steps = fe.isotropic_stage(P0, ISO_STEPS) + fe.shear_stage(P0, shear_steps * 1e-3, shear_steps)
    run_steps = steps if limit is None else steps[:limit]
    start = time.perf_counter()
    clock = [start]

    def progress(k, result):
        now = time.perf_counter()
        print(f"  {name} step {k + 1}/{len(run_steps)} ({result.stage}): q/p0 = "
              f"{(result.sigma11 - result.sigma22) / P0:.4f}, {result.iterations} iterations, residual "
              f"{result.residuals[-1]:.2e} N/m, {now - clock[0]:.1f} s", flush=True)
        clock[0] = now

    results = specimen.run(material, run_steps, scale=P0, progress=progress)
    wall = time.perf_counter() - start
    updates = sum(r.iterations + 1 for r in results)
    substeps = sum(r.diagnostics.get("substeps", 0.0) for r in results)
    iterations = np.array([r.iterations for r in results])
    shear = np.array([r.stage == "shear" for r in results])
    q = np.array([r.sigma11 - r.sigma22 for r in results]) / P0
    return {"backend": name, "points": specimen.n_points, "cells": material.n_cells, "steps_run": len(results),
            "steps_total": len(steps), "wall_s": wall,
            "wall_full_s": wall * len(steps) / len(results), "extrapolated": len(results) < len(steps),
            "iterations_mean": float(iterations.mean()), "iterations_max": int(iterations.max()),
            "shear_iterations_mean": float(iterations[shear].mean()) if shear.any() else None,
            "updates": updates, "point_updates_per_s": updates * specimen.n_points / wall,
            "cell_steps_per_s": updates * material.n_cells / wall,
            "cell_substeps_per_s": substeps / wall if substeps else None,
            "peak_q_over_p0": float(q.max()), "final_q_over_p0": float(q[-1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=element_counts, default=(32, 64))
    parser.add_argument("--orientations", type=int, default=72)
    parser.add_argument("--shear-steps", type=int, default=100)
    parser.add_argument("--backends", nargs="+", default=["analytical", "ann", "dem"])
    parser.add_argument("--dem-steps", type=int, default=None, help="load steps of the DEM run (None: all)")
    parser.add_argument("--ann-steps", type=int, default=None, help="load steps of the ANN run (None: all)")
    parser.add_argument("--analytical-steps", type=int, default=None, help="load steps of the closed-form run (None: all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    nx, ny = args.elements
    print(f"load average before: {os.getloadavg()}; {nx} x {ny} elements, {args.orientations} orientations, "
          f"{ISO_STEPS} + {args.shear_steps} steps", flush=True)
    rows = []
    for name in args.backends:
        limit = {"dem": args.dem_steps, "ann": args.ann_steps, "analytical": args.analytical_steps}.get(name)
        rows.append(run_backend(name, nx, ny, args.orientations, args.shear_steps, limit))
        print(f"load average: {os.getloadavg()}", flush=True)
    print("backend | points | cells | steps run / total | wall [s] | wall, whole programme [s] | Newton its/step "
          "(mean, max) | material-point updates/s | cell-steps/s | cell-substeps/s")
    for r in rows:
        full = f"{r['wall_full_s']:.0f}" + (" (extrapolated)" if r["extrapolated"] else "")
        sub = "-" if r["cell_substeps_per_s"] is None else f"{r['cell_substeps_per_s']:.3g}"
        print(f"{r['backend']} | {r['points']} | {r['cells']} | {r['steps_run']} / {r['steps_total']} | "
              f"{r['wall_s']:.1f} | {full} | {r['iterations_mean']:.2f}, {r['iterations_max']} | "
              f"{r['point_updates_per_s']:.3g} | {r['cell_steps_per_s']:.3g} | {sub}")
    print(f"load average after: {os.getloadavg()}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"load_after": os.getloadavg(), "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
