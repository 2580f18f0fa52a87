"""python benchmarks/bench_dem_kernel.py [--sizes 1e3,1e4,1e5,3e5] [--increment 1e-5]

Throughput of the meso-DEM cell step (H-cells), in cell-substeps per second: the Warp kernel
on 1 and 2 CPU threads and the numpy oracle of the same step (``tests/dem_oracle.py``), side by side, plus YADE if
``benchmarks/results/yade_throughput.json`` exists (key ``cell_substeps_per_s``).

Each size: cells with random alpha0 in [35, 80] deg are compressed isotropically (not
timed), then one increment of magnitude ``--increment`` in a random direction per cell is
timed (best of ``--repeat``) from that same state for every engine; substeps are counted by
the kernel (driven + relaxation). Only the integrator step is timed (no response or
observables). Rates are per wall-clock second; the Warp 1-thread rate per CPU-second is
printed too, and the machine load (``os.getloadavg``), since a shared machine makes
wall-clock timings noisy.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from warp_hcell.core.cli import positive_float, positive_int

RESULTS = Path(__file__).resolve().parent / "results"


def _sizes(text: str) -> list[int]:
    try:
        sizes = [int(float(v)) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sizes {text!r}: expected comma-separated numbers") from None
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"--sizes {text!r}: sizes must be >= 1")
    return sizes


def prepared_batch(n_cells: int, increment: float, device: str):
    """H-cells with random alpha0 in [35, 80] deg after an isotropic compression of 1e-4, and the
    timed increment (magnitude ``increment``, random direction per cell)."""
    from warp_hcell.dem.integrator import DemIntegrator
    from warp_hcell.dem.state import DemState

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from dem_oracle import h_cell_model  # vectorised H-cells: no Mesostructure per cell

    rng = np.random.default_rng(0)
    model = h_cell_model(rng.uniform(35.0, 80.0, n_cells), n_cells, 0.5, device=device)
    state = DemState.empty(n_cells, model.meso.n_grains, model.meso.n_pairs, model.device)
    DemIntegrator(model, threads=2).step(model.state(), state, np.full((n_cells, 2), 1e-4))
    angle = rng.uniform(0.0, 2.0 * np.pi, n_cells)
    return model, state, increment * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def measure(model, state, d_eps, engine: str, threads: int, repeat: int) -> tuple[float, float, float]:
    """Best wall time [s], its CPU time [s] and the mean substeps per cell of one step."""
    from warp_hcell.dem.integrator import DemIntegrator
    from warp_hcell.dem.state import DemState

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from dem_oracle import NumpyIntegrator  # the numpy oracle of the kernel, kept with the tests

    integrator = DemIntegrator(model, threads=threads) if engine == "warp" else NumpyIntegrator(model)
    out = DemState.empty(model.n_cells, model.meso.n_grains, model.meso.n_pairs, model.device)
    best = (np.inf, np.inf)
    for _ in range(repeat):
        wall, cpu = time.perf_counter(), time.process_time()
        integrator.step(state, out, d_eps)
        best = min(best, (time.perf_counter() - wall, time.process_time() - cpu))
    return best[0], best[1], float(out.substeps.numpy().mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[2],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--sizes", type=_sizes, default=_sizes("1e3,1e4,1e5,3e5"), help="numbers of cells")
    parser.add_argument("--increment", type=positive_float, default=1e-5, help="strain increment magnitude [-]")
    parser.add_argument("--repeat", type=positive_int, default=3, help="timed repetitions (best kept)")
    parser.add_argument("--numpy-max-cells", type=positive_int, default=100_000, help="largest batch run with numpy")
    parser.add_argument("--device", default="cpu", help="Warp device")
    parser.add_argument("--out", type=Path, default=None, help="optional JSON file for the results")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    wp.init()
    print(f"load average {os.getloadavg()}, {os.cpu_count()} CPUs, device {args.device}, "
          f"increment {args.increment:g}, best of {args.repeat}")
    yade_file = RESULTS / "yade_throughput.json"
    yade = json.loads(yade_file.read_text())["cell_substeps_per_s"] if yade_file.exists() else None
    cuda = wp.get_device(args.device).is_cuda
    runs = [("warp 1 thread", "warp", 1)] + ([] if cuda else [("warp 2 threads", "warp", 2)]) + [("numpy", "numpy", 1)]
    print(f"{'cells':>8} {'substeps/cell':>13} " + " ".join(f"{name:>15}" for name, _, _ in runs)
          + "   (cell-substeps/s)   ratios")
    results = []
    for n in args.sizes:
        model, state, d_eps = prepared_batch(n, args.increment, args.device)
        row = {"n_cells": n}
        for name, engine, threads in runs:
            if engine == "numpy" and (n > args.numpy_max_cells or cuda):
                continue
            wall, cpu, substeps = measure(model, state, d_eps, engine, threads,
                                          args.repeat if engine == "warp" else 1)
            row[name] = n * substeps / wall
            row[name + " per CPU-second"] = n * substeps / cpu
            row["substeps_per_cell"] = substeps
        results.append(row)
        rates = " ".join(f"{row[name]:15.3e}" if name in row else f"{'-':>15}" for name, _, _ in runs)
        ratios = [f"1T per CPU-s {row['warp 1 thread per CPU-second']:.3e}"]
        if "warp 2 threads" in row:
            ratios.append(f"2T/1T {row['warp 2 threads'] / row['warp 1 thread']:.2f}")
        if "numpy" in row:
            ratios.append(f"warp1T/numpy {row['warp 1 thread'] / row['numpy']:.0f}")
        if yade:
            ratios.append(f"warp1T/YADE {row['warp 1 thread'] / yade:.0f}")
        print(f"{n:8d} {row['substeps_per_cell']:13.1f} {rates}   " + ", ".join(ratios), flush=True)
    print(f"YADE: {yade:.3e} cell-substeps/s (from {yade_file})" if yade else f"YADE: no {yade_file.name} found")
    print(f"load average after: {os.getloadavg()}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"increment": args.increment, "yade": yade, "rows": results}, indent=1))


if __name__ == "__main__":
    main()
