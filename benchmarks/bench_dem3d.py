"""python benchmarks/bench_dem3d.py [--cells 1000] [--increment 1e-5] [--repeat 5]

Throughput of the meso-DEM cell step per CPU thread, planar and spatial cells side by side, in
cell-substeps per second (of wall clock, and of CPU time, which a loaded machine disturbs less): the
six-disk H-cell (15 candidate pairs) and the ten-sphere H-cell (45 candidate pairs) on one thread.

Each kind: ``--cells`` cells with random alpha0 in [46, 80] deg are compressed isotropically by 1e-4
(not timed), then one increment of magnitude ``--increment`` in a random direction per cell is timed
(best of ``--repeat``) from that state; substeps are counted by the kernel (driven + relaxation). The
machine load (``os.getloadavg``) is printed with the numbers. One JSON line per kind, then the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from warp_hcell.core.cli import Parser, positive_float, positive_int


def prepared(spec: str, n_cells: int, increment: float):
    """The DEM cell backend, a compressed state of ``n_cells`` cells of ``spec`` and the timed increment."""
    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.builders import resolve_mesostructure

    rng = np.random.default_rng(0)
    alpha0 = rng.uniform(46.0, 80.0, n_cells)
    cells = [resolve_mesostructure(spec, alpha0_deg=float(a)) for a in alpha0]
    dim = cells[0].dim
    dem = make_cell_model("dem", dim=dim, threads=1)
    state, _ = dem.step(dem.init_state(cells, n_cells), np.full((n_cells, dim), 1e-4))
    direction = rng.normal(size=(n_cells, dim))
    return dem, state, increment * direction / np.linalg.norm(direction, axis=1, keepdims=True)


def measure(dem, state, d_eps, repeat: int) -> dict[str, float]:
    """Best wall time of one step [s], its CPU time [s] and the mean substeps per cell."""
    best, cpu, substeps = np.inf, np.nan, np.nan
    for _ in range(repeat):
        wall0, cpu0 = time.perf_counter(), time.process_time()
        new, response = dem.step(state, d_eps)
        wall, spent = time.perf_counter() - wall0, time.process_time() - cpu0
        if wall < best:
            best, cpu, substeps = wall, spent, response.diagnostics["substeps"] / d_eps.shape[0]
    return {"wall_s": best, "cpu_s": cpu, "substeps_per_cell": substeps}


def main(argv: list[str] | None = None) -> int:
    parser = Parser(description=__doc__.splitlines()[2])
    parser.add_argument("--cells", type=positive_int, default=1000, help="cells per batch")
    parser.add_argument("--increment", type=positive_float, default=1e-5, help="magnitude of the timed increment [-]")
    parser.add_argument("--repeat", type=positive_int, default=5, help="timed repetitions (best kept)")
    args = parser.parse_args(argv)
    rates = {}
    for kind, spec in (("2D six-disk H-cell", "hcell"), ("3D ten-sphere H-cell", "hcell3d")):
        dem, state, d_eps = prepared(spec, args.cells, args.increment)
        dem.step(state, d_eps)  # compile / warm up
        timing = measure(dem, state, d_eps, args.repeat)
        work = args.cells * timing["substeps_per_cell"]
        rates[kind] = work / timing["cpu_s"]
        print(json.dumps({"cell": kind, "n_cells": args.cells, "n_pairs": state.model.meso.n_pairs, **timing,
                          "cell_substeps_per_s": work / timing["wall_s"],
                          "cell_substeps_per_cpu_s": rates[kind], "load": os.getloadavg()[0]}))
    two, three = rates.values()
    print(f"one thread, per CPU-second: 2D {two:.3g} vs 3D {three:.3g} cell-substeps/s, 3D/2D = {three / two:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
