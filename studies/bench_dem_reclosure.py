"""python studies/bench_dem_reclosure.py [--rates 5e-6,2e-6,1e-6,5e-7,2.5e-7] [--out FILE]

Contacts that close again (docs/dem_stepping.md, "Contacts that close again"), two tables:

- the DEM on the committed YADE cases ``reclose_a60_*`` (tests/data/yade) for each
  ``closing_strain_per_substep`` of ``--rates``, and the closed form: largest |N1|, |N2|, |T1|
  error over the case's largest force, on every row and outside YADE's snap-through row and one
  row either side, with the DEM substeps of the path;
- the DEM (defaults) against the closed form on the constant-volume +5 % / -10 % test at
  alpha0 = 60 deg, p0 = 2e5 N/m: max |dp|, |dq| / p0 before the first re-closure, between it
  and the last collapse of a wedge, and from two increments after it.

Writes the numbers as JSON (default ``studies/results/dem_reclosure.json``).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from homogenization.element_test import driver, programme as programmes
from homogenization.backends import make_cell_model
from warp_hcell.core.parameters import CellDefaults, ContactLaw, DemSettings
from warp_hcell.mesostructures.hcell import h_cell

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "studies" / "results"
MACRO_RUNS = ((18, 1e-3), (36, 1e-3), (36, 5e-4))
"""(orientations, shear increment) of the macro comparisons."""


def _load(module: str, path: Path):
    spec = importlib.util.spec_from_file_location(module, path)
    loaded = importlib.util.module_from_spec(spec)
    sys.modules[module] = loaded
    spec.loader.exec_module(loaded)
    return loaded


def cell_errors(backend: str, name: str, reference, **options) -> dict[str, float]:
    """Error / largest force of one backend along the YADE case ``name``, every row and outside
    the snap-through window of ``tests/test_yade_reference.py`` (YADE's snap-through row and one row
    either side), and the DEM substeps."""
    path, yade, meta = reference.load_case(name)
    model = make_cell_model(backend, contact_law=ContactLaw(), radius=CellDefaults.radius, **options)
    state = model.init_state(h_cell(meta["alpha0_deg"], CellDefaults.radius), 1)
    error = np.zeros(len(path))
    substeps = 0
    for row, d_eps in enumerate(path):
        state, _ = model.step(state, d_eps[None, :])
        observed = model.observables(state)
        error[row] = max(abs(float(observed[key][0]) - yade[key][row]) for key in ("N1", "N2", "T1"))
        substeps += int(observed.get("substeps", np.zeros(1))[0])
    error /= reference._force_scale(yade)
    snap = reference._snap_rows(yade, meta["alpha0_deg"])
    return {"max": float(error.max()), "outside_snap": float(np.where(snap, 0.0, error).max()), "substeps": substeps}


def macro_windows(n_orientations: int, increment: float, reference) -> dict[str, float]:
    """DEM vs closed form on the alpha0 = 60 deg reversal, max |dp|, |dq| / p0 per window."""
    p0 = 2e5
    programme = (programmes.isotropic(p0, increment=1e-3),
                 programmes.constant_volume_biaxial(0.05, round(0.05 / increment), label="load"),
                 programmes.constant_volume_biaxial(-0.10, round(0.10 / increment), label="unload"))
    runs = {name: driver.run(make_cell_model(name), programme, mesostructure=h_cell(60.0),
                             n_orientations=n_orientations, snapshot_interval=1, progress=False)
            for name in ("analytical", "dem")}
    windows = [reference._reclosure_and_collapse(run) for run in runs.values()]
    first, last = min(w[0] for w in windows), max(w[1] for w in windows)
    error = np.maximum(np.abs(runs["dem"].p - runs["analytical"].p), np.abs(runs["dem"].q - runs["analytical"].q)) / p0
    return {"orientations": n_orientations, "increment": increment, "first_reclosure": first, "last_collapse": last,
            "before": float(error[:first].max()), "between": float(error[first:last + 2].max()),
            "after": float(error[last + 2:].max())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--rates", default="5e-6,2e-6,1e-6,5e-7,2.5e-7", help="closing_strain_per_substep values")
    parser.add_argument("--out", type=Path, default=RESULTS / "dem_reclosure.json", help="JSON output")
    args = parser.parse_args(argv)
    try:
        rates = [float(v) for v in args.rates.split(",")]
        if not rates or min(rates) <= 0.0:
            raise ValueError
    except ValueError:
        print(f"error: --rates {args.rates!r}: expected comma-separated positive numbers", file=sys.stderr)
        return 2
    sys.path.insert(0, str(ROOT / "tests"))
    yade_reference = _load("test_yade_reference", ROOT / "tests" / "test_yade_reference.py")
    vs_analytical = _load("test_homogenization_dem_vs_analytical",
                          ROOT / "tests" / "test_homogenization_dem_vs_analytical.py")
    results = {"cells": {}, "macro": []}
    warnings.simplefilter("error", RuntimeWarning)  # an unconverged DEM cell stops the benchmark
    for name in yade_reference.RECLOSE_NAMES:
        rows = {"closed form": cell_errors("analytical", name, yade_reference)}
        for rate in rates:
            rows[f"DEM closing {rate:g}"] = cell_errors("dem", name, yade_reference,
                                                        settings=DemSettings(closing_strain_per_substep=rate))
        results["cells"][name] = rows
        print(f"{name}: error / largest force (every row, outside the snap-through window), DEM substeps")
        for label, row in rows.items():
            print(f"  {label:22s} {row['max']:.2e}  {row['outside_snap']:.2e}  {row['substeps']}")
    print("alpha0 = 60 deg, CV +5 % / -10 %: DEM vs closed form, max(|dp|, |dq|) / p0")
    for n_orientations, increment in MACRO_RUNS:
        row = macro_windows(n_orientations, increment, vs_analytical)
        results["macro"].append(row)
        print(f"  {n_orientations} orientations, increment {increment:g}: before re-closure {row['before']:.2e}, "
              f"between {row['between']:.2e}, after the last collapse {row['after']:.2e}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
