"""python benchmarks/bench_bvp.py [--elements 32,64] [--orientations N] [--shear-steps 100] [--dem-steps K] [--out FILE]

Speed of the finite-element biaxial specimen (``homogenization.fe.solver``) at scale, the
closed-form (analytical), meso-ANN and meso-DEM backends side by side in one run, on one mesh
(default 32 x 64 bilinear quadrilaterals, 2 x 2 Gauss points: 8 192 material points) with
--orientations cells per point: alpha0 = 40 deg, p0 = 2e5 N/m, 20 isotropic steps, then
--shear-steps steps of 1e-3 (through the peak at about 3.5 %). Every Newton iteration is one
batched material update of all points. Backend ``dem`` defers its tangent (computed only for a
Newton correction) and reuses it while it contracts (``reuse_tangent``); ``dem:deferred`` defers
it without reuse; ``dem:eager`` computes it with every update (the solver before deferral), so
--backends dem:eager dem:deferred dem compares the three in one run (CPU and wall ratios printed).

Per backend: load steps run (iso + shear), wall and CPU time [s], the wall split into material
updates (the cells' step, with the tangent where the backend computes it with the step), deferred
tangents and the rest (FE assembly and solve, observables),
Newton iterations per step (iso, shear), material updates, tangents computed and reused,
material-point updates/s, cell-substeps/s and substeps per cell and update (the DEM's
``substeps``), and the DEM's cells left unconverged. ``--dem-steps K`` (and ``--ann-steps``,
``--analytical-steps``) run only the first K load steps of that backend; the whole programme's
wall is then extrapolated (labelled) from the mean wall per step of each stage run, so K should
reach into the shear stage. Prints the machine load before and after each backend (shared machine).
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


class EagerTangent:
    """A cell model without ``step_tangent``: the material asks every step for its tangent."""

    def __init__(self, model) -> None:
        self.model, self.name = model, model.name

    def step(self, cells, d_eps, *, with_tangent=False):
        return self.model.step(cells, d_eps, with_tangent=with_tangent)

    def __getattr__(self, name):
        if name == "step_tangent":
            raise AttributeError(name)
        return getattr(self.model, name)


class Timed:
    """Wall time spent in a material's ``update`` and ``tangent`` (wrapped on the instance)."""

    def __init__(self, material: HomogenisedMaterial) -> None:
        self.update_s = self.tangent_s = 0.0
        update, tangent = material.update, material.tangent

        def timed_update(*args, **kwargs):
            start = time.perf_counter()
            try:
                return update(*args, **kwargs)
            finally:
                self.update_s += time.perf_counter() - start

        def timed_tangent(*args, **kwargs):
            start = time.perf_counter()
            try:
                return tangent(*args, **kwargs)
            finally:
                self.tangent_s += time.perf_counter() - start

        material.update, material.tangent = timed_update, timed_tangent


def run_backend(name: str, nx: int, ny: int, n_orientations: int, shear_steps: int, limit: int | None) -> dict:
    """One homogeneous run of backend ``name`` (module docstring), the first ``limit`` load steps (None: all)."""
    backend, _, variant = name.partition(":")
    specimen = fe.BiaxialSpecimen(nx, ny, newton_rtol=RTOL[backend], reuse_tangent=backend == "dem" and not variant)
    model = make_cell_model(backend)
    if variant == "eager":
        model = EagerTangent(model)
    material = HomogenisedMaterial(model, orientation.orientations(n_orientations), h_cell(ALPHA0), specimen.n_points)
    timed = Timed(material)
    steps = fe.isotropic_stage(P0, ISO_STEPS) + fe.shear_stage(P0, shear_steps * 1e-3, shear_steps)
    run_steps = steps if limit is None else steps[:limit]
    load_before = os.getloadavg()
    start, cpu_start = time.perf_counter(), time.process_time()
    clock = [start]
    step_wall: list[float] = []

    def progress(k, result):
        now = time.perf_counter()
        step_wall.append(now - clock[0])
        sub = result.diagnostics.get("substeps", 0.0) / material.n_cells / (result.iterations + 1)
        print(f"  {name} step {k + 1}/{len(run_steps)} ({result.stage}): q/p0 = "
              f"{(result.sigma11 - result.sigma22) / P0:.4f}, {result.iterations} iterations, tangents "
              f"{result.diagnostics.get('tangents', 0):g} (+{result.diagnostics.get('tangents_reused', 0):g} reused), "
              f"{sub:.1f} substeps/cell/update, residual {result.residuals[-1]:.2e} N/m, {now - clock[0]:.1f} s, "
              f"CPU so far {time.process_time() - cpu_start:.1f} s, load {os.getloadavg()[0]:.1f}", flush=True)
        clock[0] = now

    results = specimen.run(material, run_steps, scale=P0, progress=progress)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    iterations = np.array([r.iterations for r in results])
    updates = iterations + 1
    shear = np.array([r.stage == "shear" for r in results])
    walls = np.array(step_wall)
    n_shear_total = len(steps) - ISO_STEPS
    if shear.any() and (~shear).any():
        wall_full = walls[~shear].mean() * ISO_STEPS + walls[shear].mean() * n_shear_total
    else:
        wall_full = wall * len(steps) / len(results)
    def diag(key: str, mask: np.ndarray | None = None) -> float:
        """Diagnostic ``key`` summed over the steps (where ``mask``)."""
        return float(sum(r.diagnostics.get(key, 0.0) for k, r in enumerate(results) if mask is None or mask[k]))

    def per_update(mask: np.ndarray) -> float:
        """Substeps per cell and material update over the steps where ``mask``."""
        return diag("substeps", mask) / material.n_cells / max(int(updates[mask].sum()), 1)

    substeps = diag("substeps")
    q = np.array([r.sigma11 - r.sigma22 for r in results]) / P0
    return {"backend": name, "points": specimen.n_points, "cells": material.n_cells,
            "reuse_tangent": specimen.reuse_tangent,
            "steps_run": len(results), "iso_steps_run": int((~shear).sum()), "shear_steps_run": int(shear.sum()),
            "steps_total": len(steps), "wall_s": wall, "cpu_s": cpu, "update_s": timed.update_s,
            "tangent_s": timed.tangent_s, "rest_s": wall - timed.update_s - timed.tangent_s,
            "wall_full_s": wall_full if len(results) < len(steps) else wall,
            "extrapolated": len(results) < len(steps), "load_before": load_before, "load_after": os.getloadavg(),
            "iso_iterations_mean": float(iterations[~shear].mean()) if (~shear).any() else None,
            "shear_iterations_mean": float(iterations[shear].mean()) if shear.any() else None,
            "iterations_max": int(iterations.max()), "updates": int(updates.sum()),
            "tangents": diag("tangents"), "tangents_reused": diag("tangents_reused"),
            "point_updates_per_s": int(updates.sum()) * specimen.n_points / wall,
            "cell_substeps_per_s": substeps / wall if substeps else None,
            "substeps_per_cell_update_iso": per_update(~shear) if substeps and (~shear).any() else None,
            "substeps_per_cell_update_shear": per_update(shear) if substeps and shear.any() else None,
            "n_unconverged_cells": diag("n_unconverged"), "line_search_halvings": diag("line_search_halvings"),
            "peak_q_over_p0": float(q.max()), "final_q_over_p0": float(q[-1]),
            "q_over_p0": q.tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=element_counts, default=(32, 64))
    parser.add_argument("--orientations", type=int, default=72)
    parser.add_argument("--shear-steps", type=int, default=100)
    parser.add_argument("--backends", nargs="+", default=["analytical", "ann", "dem"])
    parser.add_argument("--dem-steps", type=int, default=None, help="load steps of the DEM run (None: all)")
    parser.add_argument("--ann-steps", type=int, default=None, help="load steps of the ANN run (None: all)")
    parser.add_argument("--analytical-steps", type=int, default=None,
                        help="load steps of the closed-form run (None: all)")
    parser.add_argument("--out", type=Path, default=None, help="also write the rows as JSON")
    args = parser.parse_args()
    nx, ny = args.elements
    print(f"load average before: {os.getloadavg()}; {nx} x {ny} elements, {args.orientations} orientations, "
          f"{ISO_STEPS} + {args.shear_steps} steps; CPUs {os.cpu_count()}", flush=True)
    rows = []
    for name in args.backends:
        limit = {"dem": args.dem_steps, "ann": args.ann_steps,
                 "analytical": args.analytical_steps}.get(name.partition(":")[0])
        rows.append(run_backend(name, nx, ny, args.orientations, args.shear_steps, limit))
        print(f"load average: {os.getloadavg()}", flush=True)
        if args.out is not None:  # after each backend: a long run keeps what it measured
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps({"load_after": os.getloadavg(), "rows": rows}, indent=1) + "\n")
    print("backend | points | cells | steps run (iso + shear) / total | wall [s] (updates, tangents, rest) | CPU [s] | "
          "wall, whole programme [s] | Newton its/step (iso, shear; max) | updates | tangents computed (reused) | "
          "material-point updates/s | cell-substeps/s | substeps/cell/update (iso, shear) | unconverged cells | load")
    for r in rows:
        full = f"{r['wall_full_s']:.0f}" + (" (extrapolated)" if r["extrapolated"] else "")
        sub = "-" if r["cell_substeps_per_s"] is None else f"{r['cell_substeps_per_s']:.3g}"
        per = "-" if r["substeps_per_cell_update_shear"] is None and r["substeps_per_cell_update_iso"] is None else \
            ", ".join("-" if v is None else f"{v:.1f}" for v in (r["substeps_per_cell_update_iso"],
                                                                 r["substeps_per_cell_update_shear"]))
        its = ", ".join("-" if v is None else f"{v:.2f}"
                        for v in (r["iso_iterations_mean"], r["shear_iterations_mean"]))
        print(f"{r['backend']} | {r['points']} | {r['cells']} | {r['iso_steps_run']} + {r['shear_steps_run']} / "
              f"{r['steps_total']} | {r['wall_s']:.1f} ({r['update_s']:.1f}, {r['tangent_s']:.1f}, "
              f"{r['rest_s']:.1f}) | "
              f"{r['cpu_s']:.1f} | {full} | {its}; {r['iterations_max']} | {r['updates']} | {r['tangents']:g} "
              f"({r['tangents_reused']:g}) | {r['point_updates_per_s']:.3g} | {sub} | {per} | "
              f"{r['n_unconverged_cells']:g} | {r['load_before'][0]:.1f} -> {r['load_after'][0]:.1f}")
    base = next((r for r in rows if r["backend"] == "dem:eager"), None)
    for r in rows:
        same = base is not None and r is not base and r["steps_run"] == base["steps_run"]
        if same and r["backend"].startswith("dem"):
            dq = np.abs(np.subtract(r["q_over_p0"], base["q_over_p0"])).max()
            print(f"{r['backend']} / dem:eager: wall {r['wall_s'] / base['wall_s']:.3f}, "
                  f"CPU {r['cpu_s'] / base['cpu_s']:.3f}, max |q - q_eager| / p0 = {dq:.2g}")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
