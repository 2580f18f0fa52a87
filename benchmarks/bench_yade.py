"""Run: python benchmarks/bench_yade.py [--n-cells 1 100 1000 10000] [--threads 1 2] [--seconds 5]

YADE throughput on many independent six-disk H-cells in one scene, the number the Warp DEM
benchmark compares against. For each thread count and cell count this launches
``yade -jT -n -x benchmarks/bench_yade.py --worker ...``; the worker builds the cells with
``HCellScene`` of tests/yade/hcell_paths.py (same contact law, damping, dt, driven/free
DOFs and 2.5e-7 strain per substep as the reference cases), compresses them isotropically
by 1e-4 so that every contact carries force (no relaxation: it is not what is measured),
then times constant-volume rows (+-5e-5, -+5e-5, alternating) for about ``--seconds`` (at
least one row of 200 substeps).
Only the substeps are timed (O.step calls); setting the row velocities is not. Multi-thread
runs are made with OMP_WAIT_POLICY=PASSIVE and ACTIVE: spinning OpenMP barriers (ACTIVE,
libgomp's default behaviour) collapse when the cores are shared with other work.

Measured: cell-substeps per second = n_cells * substeps / wall time, and per CPU second of
the process (all its threads; on a busy machine, the -j1 rate per CPU second estimates
what an idle core would give). Writes
benchmarks/results/yade_throughput.json with ``cell_substeps_per_s`` (the best rate over
all runs) and every run, with the load average of the (shared) machine before and after.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "yade_throughput.json"
PRELOAD = 1e-4
"""Isotropic strain applied before timing [-] (400 substeps)."""
ROW = 5e-5
"""Strain of one timed constant-volume row [-] (200 substeps)."""


def worker(n_cells: int, seconds: float) -> dict:
    """Inside YADE: time the stepping of ``n_cells`` H-cells; return the measurement."""
    import inspect

    here = Path(inspect.currentframe().f_code.co_filename).resolve().parent
    sys.path.insert(0, str(here.parent / "tests" / "yade"))
    import numpy as np
    from hcell_paths import HCellScene
    from yade import O

    from warp_hcell.core.parameters import CellDefaults, ContactLaw, DemSettings

    start = time.perf_counter()
    scene = HCellScene(CellDefaults.alpha0_deg, n_cells, ContactLaw(), CellDefaults.radius, DemSettings())
    build_s = time.perf_counter() - start
    scene.drive(np.array([PRELOAD, PRELOAD]))
    n_contacts = sum(1 for i in O.interactions if i.isReal and i.phys.normalForce.norm() > 0.0)
    substeps, wall, cpu, sign = 0, 0.0, 0.0, 1.0
    while wall < seconds:
        n_sub = scene.start_row(np.array([sign * ROW, -sign * ROW]))
        tic, cpu_tic = time.perf_counter(), time.process_time()
        for _ in range(n_sub):
            O.step()
        wall += time.perf_counter() - tic
        cpu += time.process_time() - cpu_tic
        scene.finish_row()
        substeps += n_sub
        sign = -sign
    return {
        "n_cells": n_cells,
        "omp_threads": int(O.numThreads),
        "substeps": substeps,
        "wall_s": wall,
        "cell_substeps_per_s": n_cells * substeps / wall,
        "cpu_s": cpu,
        "cell_substeps_per_cpu_s": n_cells * substeps / cpu,
        "us_per_substep": 1e6 * wall / substeps,
        "loaded_contacts": n_contacts,
        "build_s": build_s,
    }


def launch(n_cells: int, threads: int, seconds: float, wait_policy: str) -> dict:
    """Run one worker under ``yade -j<threads>`` with OMP_WAIT_POLICY=``wait_policy``; return its measurement."""
    command = ["yade", f"-j{threads}", "-n", "-x", str(Path(__file__).resolve()), "--worker"]
    command += ["--n-cells", str(n_cells), "--seconds", str(seconds)]
    env = {**os.environ, "OMP_WAIT_POLICY": wait_policy}
    done = subprocess.run(command, check=True, capture_output=True, text=True, cwd=HERE.parent, env=env)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if not lines:
        raise RuntimeError(f"yade worker printed no result:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    result = json.loads(lines[-1][len("RESULT ") :])
    result["threads"] = threads
    result["omp_wait_policy"] = wait_policy
    return result


def main(argv: list[str]) -> int:
    """Entry point; returns the exit code."""
    parser = argparse.ArgumentParser(
        prog="python benchmarks/bench_yade.py",
        description="YADE throughput of many six-disk H-cells (cell-substeps per second).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--n-cells", type=int, nargs="+", default=[1, 100, 1000, 10000], help="cells per scene")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="yade -j values")
    parser.add_argument("--seconds", type=float, default=5.0, help="timed stepping per run [s]")
    parser.add_argument(
        "--omp-wait-policy",
        nargs="+",
        choices=["PASSIVE", "ACTIVE"],
        default=["PASSIVE", "ACTIVE"],
        help="OpenMP wait policies to run (ACTIVE spins at barriers, which collapses on a busy machine)",
    )
    parser.add_argument("--out", type=Path, default=RESULTS, help="JSON results file")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args([a for a in argv if a != "--"])
    if args.worker:
        print("RESULT " + json.dumps(worker(args.n_cells[0], args.seconds)), flush=True)
        return 0
    if shutil.which("yade") is None:
        print("error: yade is not on PATH", file=sys.stderr)
        return 2
    version = subprocess.run(["yade", "--version"], capture_output=True, text=True).stdout.strip()
    load_before = os.getloadavg()
    runs = []
    for threads in args.threads:
        for policy in args.omp_wait_policy if threads > 1 else args.omp_wait_policy[:1]:
            for n_cells in args.n_cells:
                run = launch(n_cells, threads, args.seconds, policy)
                runs.append(run)
                print(
                    f"-j{threads} {policy:7s} {n_cells:6d} cells: {run['cell_substeps_per_s']:.3e} cell-substeps/s "
                    f"({run['us_per_substep']:.1f} us per substep, {run['substeps']} substeps; "
                    f"{run['cell_substeps_per_cpu_s']:.3e} per CPU second)",
                    flush=True,
                )
    best = max(runs, key=lambda r: r["cell_substeps_per_s"])
    result = {
        "cell_substeps_per_s": best["cell_substeps_per_s"],
        "best": {key: best[key] for key in ("n_cells", "threads", "omp_wait_policy")},
        "runs": runs,
        "yade_version": version,
        "setup": (
            "independent six-disk H-cells in one YADE scene (tests/yade/hcell_paths.py HCellScene), "
            "FrictMat/CundallStrack, rotations blocked, damping and dt from DemSettings, "
            "2.5e-7 strain per substep, constant-volume rows of +-5e-5 after isotropic 1e-4; only O.step timed"
        ),
        "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count()},
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"best {best['cell_substeps_per_s']:.3e} cell-substeps/s ({result['best']})")
    print(f"load average before {load_before}, after {result['load_average_after']}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    code = main(sys.argv[1:])
    if code:
        sys.exit(code)
