"""python benchmarks/bench_sweep.py [--orientations 72] [--increment 1e-4] [--eps-max 0.15] [--out runs/bench_sweep]

Wall time of a 16-case DEM sweep (4 mesostructures x alpha0 50, 55 x p0 2e5, 5.85e6; issue 12)
run with 2 workers (a Dask LocalCluster, ``warp_hcell.core.execution``) and with 1 worker (in
process), one after the other: prints, per run, the wall time (cluster start-up included), the
CPU time of the sweep's processes, the load average before it, and the ratio of the two wall
times; checks that both summaries are byte-identical. The machine may be shared:
read the timings with the load average. Writes its sweep folders under --out (replaced).
"""

from __future__ import annotations

import argparse
import filecmp
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

MESOSTRUCTURES = "hcell,hcell-fines:ratio=0.6,hcell-fines:ratio=0.76,hcell-fines:ratio=0.8"


def run(args: argparse.Namespace, workers: int) -> tuple[float, float, str, Path]:
    out = args.out / f"w{workers}"
    shutil.rmtree(out, ignore_errors=True)
    command = [sys.executable, "-m", "homogenization.sweep", "--mesostructure", MESOSTRUCTURES, "--alpha0", "50,55",
               "--p0", "2e5,5.85e6", "--backend", "dem", "--eps-max", str(args.eps_max), "--increment",
               str(args.increment), "--iso-increment", str(args.increment), "--orientations", str(args.orientations),
               "--workers", str(workers), "--out", str(out)]
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else ["?"] * 3
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, " / ".join(load), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--orientations", type=int, default=72)
    parser.add_argument("--increment", type=float, default=1e-4)
    parser.add_argument("--eps-max", type=float, default=0.15)
    parser.add_argument("--out", type=Path, default=Path("runs/bench_sweep"))
    args = parser.parse_args()
    os.environ.setdefault("MPLBACKEND", "Agg")
    results = {workers: run(args, workers) for workers in (2, 1)}
    print(f"16 cases, {args.orientations} orientations, increment {args.increment:g}, to eps1 = {args.eps_max:g}")
    print("| workers | wall [s] | CPU [s] | load average before (1 / 5 / 15 min) |")
    print("|---|---|---|---|")
    for workers, (wall, cpu, load, _) in results.items():
        print(f"| {workers} | {wall:.1f} | {cpu:.1f} | {load} |")
    print(f"wall(1 worker) / wall(2 workers) = {results[1][0] / results[2][0]:.2f}")
    same = filecmp.cmp(results[1][3] / "summary.csv", results[2][3] / "summary.csv", shallow=False)
    print(f"summaries byte-identical: {same}")


if __name__ == "__main__":
    main()
