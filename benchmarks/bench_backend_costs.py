"""python benchmarks/bench_backend_costs.py [--cells 100 1000 7792] [--increments 10] [--shear 1e-5 ...] [--fine-model PATH]: cost per cell-increment of each backend.

For each cell (the plain 2D H-cell and the plain 3D ten-sphere cell at alpha0 = 55 deg, and the 3D
cell with a fine grain ``benchmarks/cells/fine_off_centre.toml``) and each number of cells, the
backends that model it (closed form, DEM, ANN: the shipped model of the plain cells;
``--fine-model``, a model trained on the fine-grain cell, for that one) start from the cell's
rest state, take ``--warmup`` isotropic compression increments of 2e-5 per axis, then
``--increments`` timed increments of a constant-volume-like local strain (each value of ``--shear``
along n, the opposite shared by the other axes): ``step`` of all the cells at once, one thread, the
backends one after the other in one run. Prints one line per shear, cell, number of cells and
backend: the median wall time of one increment and that time per cell-increment [us], then a
Markdown table of the latter (rows: shear, cells; columns: backends), with the load average. Beside
each time, the work its increments took (``COUNTS``, the median over the timed increments): the DEM's
substeps and the hybrid ANN's Newton corrections per cell-increment, the closed form's residual
evaluations of the batch per increment. The DEM relaxes each increment to equilibrium, so its substeps
depend on the increment.

Timings are of ``CellModel.step`` alone (no stress control, no output); a whole run adds its
start-up (``benchmarks/bench_short_runs.py``) and, for stress-controlled tests, a few trial steps
per increment.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from homogenization.backends import make_cell_model, mesostructure_refusal
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.core.provenance import cpu_model
from warp_hcell.mesostructures.files import load_mesostructure

ROOT = Path(__file__).resolve().parents[1]
FINE = ROOT / "benchmarks" / "cells" / "fine_off_centre.toml"


def cells(args) -> list[tuple[str, object, dict[str, dict]]]:
    """(label, mesostructure, backend -> options) of every cell measured."""
    fine = {"dem": {"threads": 1}}
    if args.fine_model:
        fine["ann"] = {"model": args.fine_model, "threads": 1}
    return [("plain 2D H-cell", resolve_mesostructure("hcell:alpha0=55"),
             {"analytical": {}, "dem": {"threads": 1}, "ann": {"threads": 1}}),
            ("plain 3D ten-sphere cell", resolve_mesostructure("hcell3d:alpha0=55"),
             {"analytical": {}, "dem": {"threads": 1}, "ann": {"threads": 1}}),
            ("3D cell with a fine grain (fine_off_centre.toml)", load_mesostructure(FINE), fine)]


COUNTS = {"dem": ("substeps", True), "ann": ("n_corrections", True), "analytical": ("iterations", False)}
"""Backend -> (its diagnostic of the work of an increment, whether it is summed over the cells)."""


def time_backend(name: str, options: dict, meso, n: int, strain: float, args) -> tuple[float, float | None]:
    """(median wall seconds of one ``step`` of ``n`` cells of ``meso`` with shear ``strain`` [-], the median of its
    ``COUNTS`` diagnostic per increment, per cell where summed over them; None where the step reports none)."""
    model = make_cell_model(name, dim=meso.dim, **options)
    state = model.init_state(meso, n)
    iso = np.full((n, meso.dim), 2e-5)
    shear = np.full((n, meso.dim), -strain / (meso.dim - 1))
    shear[:, 0] = strain
    for _ in range(args.warmup):
        state, _ = model.step(state, iso)
    times, counts = [], []
    key, per_cell = COUNTS[name]
    for _ in range(args.increments):
        start = time.perf_counter()
        state, response = model.step(state, shear)
        times.append(time.perf_counter() - start)
        if key in response.diagnostics:
            counts.append(float(response.diagnostics[key]) / (n if per_cell else 1))
    return float(np.median(times)), (float(np.median(counts)) if counts else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--cells", type=int, nargs="+", default=[100, 1000, 7792], help="numbers of cells")
    parser.add_argument("--increments", type=int, default=10, help="timed increments per backend")
    parser.add_argument("--shear", type=float, nargs="+", default=[1e-5],
                        help="local strains along n of the timed increments [-], one table block each")
    parser.add_argument("--warmup", type=int, default=20, help="isotropic increments before the timed ones")
    parser.add_argument("--fine-model", default=None, help="an ANN model of the fine-grain cell (none is shipped)")
    args = parser.parse_args()
    if not all(0.0 < strain < 1e-2 for strain in args.shear) or min(args.cells) < 1 or args.increments < 1:
        parser.error(f"--shear {args.shear} must each be in (0, 0.01), --cells and --increments >= 1")
    if args.fine_model and not Path(args.fine_model).is_file():
        parser.error(f"--fine-model {args.fine_model}: no such file")
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; CPU: {cpu_model()}", flush=True)
    table: dict[tuple[float, str, int], dict[str, tuple[float, float | None]]] = {}
    backends: list[str] = []
    measured = cells(args)  # read once for every shear
    for strain in args.shear:
        for label, meso, options in measured:
            for n in args.cells:
                for name, opts in options.items():
                    if mesostructure_refusal(name, meso):
                        continue
                    seconds, work = time_backend(name, opts, meso, n, strain, args)
                    per = 1e6 * seconds / n
                    table.setdefault((strain, label, n), {})[name] = (per, work)
                    backends += [name] if name not in backends else []
                    print(json.dumps({"shear": strain, "cell": label, "cells": n, "backend": name,
                                      "step_ms": round(1e3 * seconds, 3), "us_per_cell_increment": round(per, 3),
                                      COUNTS[name][0]: work}), flush=True)
    print(f"\n| shear | cell | cells | {' | '.join(f'{b} [us] ({COUNTS[b][0]})' for b in backends)} |")
    print(f"|---|---|---|{'---|' * len(backends)}")
    for (strain, label, n), row in table.items():
        entries = [f"{row[b][0]:.2f} ({'-' if row[b][1] is None else f'{row[b][1]:.3g}'})" if b in row else "-"
                   for b in backends]
        print(f"| {strain:g} | {label} | {n} | {' | '.join(entries)} |")
    print(f"\nload average after: {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
