"""The meso-ANN pipeline of a new 3D cell, phase by phase: generate, train, certificate, rounds.

``python benchmarks/bench_pipeline3d.py --out DIR [--mesostructure SPEC|FILE] [--samples N]
[hmodel train options]``

Runs what a user runs: ``hmodel generate --mesostructure M --seed S --out DIR/db.h5 [--samples
N]``, then ``hmodel train --data DIR/db.h5 --out DIR/ann.pt [options]`` (its defaults: training,
the minimum certificate, the active-learning rounds), and prints the wall time of each phase
(generation; the first training; round 0's certificate; each round's probing + certificate and
its training), the database's size after each phase (on disk and uncompressed) and each round's
certificate worst, the tests the ANN could not follow and the samples the size budget left
out. The load average of the machine is printed beside the times (they are the wall times of
a shared machine). A folder of an earlier call is started again (``--overwrite``).

The train line says which surrogate the certificate measures (a 3D cell with fine grains: the
network with equilibrium corrections, by default); the last lines say how often its corrections
fired in the final certificate.

Default cell: ten equal spheres (alpha0 = 53 deg) with a free fine sphere of 0.74 r, off the
pore centre (n = 0.06 r, t2 = 0.04 r). Numbers: docs/certificate.md, "The pipeline of a 3D cell
with a fine grain" (the network alone, then the default) and "The default pipeline of a 3D cell
with fine grains" (the cells of ``benchmarks/cells``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import h5py

from homogenization.learning import certificate
from homogenization.ann.envelope import equilibrium_settings, escalation_of
from homogenization.ann.records import Certificate
from homogenization.cli import hmodel
from warp_hcell.database.format import sizes

CELL = "hcell3d-fines:alpha0=53,ratio=0.74,n=0.06,t2=0.04"
"""The default cell: one that no setting of the pipeline was tuned for."""


def _mb(path: Path) -> str:
    on_disk, raw = sizes(path)
    return f"{on_disk / 1e6:.1f} MB ({raw / 1e6:.1f} MB uncompressed)"


def _load() -> str:
    return "load %.1f %.1f %.1f" % os.getloadavg()


def surrogate_line(cert: Certificate) -> str:
    """The surrogate the certificate measured and, for the hybrid, how often its corrections fired."""
    k, tolerance = equilibrium_settings(cert)
    if not k:
        return "certified surrogate: the network alone"
    tally = cert.equilibrium
    cell_steps = int(cert.settings["n_cells"]) * int(tally["steps"])
    return (f"certified surrogate: the network + up to {k} equilibrium corrections at force ratio {tolerance:g}: "
            f"{tally['n_corrected']} of {cell_steps} cell steps corrected "
            f"({100 * tally['n_corrected'] / max(cell_steps, 1):.1f} %), "
            f"{tally['n_corrections']} Newton steps ({tally.get('n_shortened', 0)} shortened by the line search, "
            f"{tally.get('n_shifted', 0)} shifted), "
            f"{tally['n_unconverged']} left above the tolerance"
            + (f", {tally.get('n_released', 0)} with a released grain taken again at rest "
               f"({tally.get('n_released_pushed', 0)} pushed), {tally.get('n_escalated', 0)} handed to the DEM"
               if escalation_of(cert) else ""))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the run (db.h5, ann.pt, ann.json)")
    parser.add_argument("--mesostructure", default=CELL, help="3D cell: builder spec or file")
    parser.add_argument("--samples", type=int, default=None, help="samples of the generated database (its default)")
    parser.add_argument("--seed", type=int, default=0, help="seed of generate and train")
    parser.add_argument("--threads", type=int, default=1, help="DEM and torch threads")
    args, train_args = parser.parse_known_args(argv)
    if args.out.exists():
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True)
    db, model = args.out / "db.h5", args.out / "ann.pt"
    common = ["--seed", str(args.seed), "--threads", str(args.threads), "-q"]
    print(f"cell {args.mesostructure}; {_load()}")
    start = time.perf_counter()
    generate = ["generate", "--mesostructure", args.mesostructure, "--out", str(db), *common,
                *([] if args.samples is None else ["--samples", str(args.samples)])]
    if hmodel.main(generate) != 0:
        return 1
    generated = time.perf_counter() - start
    with h5py.File(db) as f:
        n_samples = int(f["d_eps"].shape[0])
    print(f"generate: {generated:.0f} s, {n_samples} samples, database {_mb(db)}; {_load()}")
    start = time.perf_counter()
    code = hmodel.main(["train", "--data", str(db), "--out", str(model), *common, *train_args])
    trained = time.perf_counter() - start
    if code not in (0, certificate.EXIT_FAILED, certificate.EXIT_WEAK):
        print(f"hmodel train exited {code}", file=sys.stderr)
        return code
    meta = json.loads(model.with_suffix(".json").read_text())
    rounds = meta["active_learning"]
    first_training = trained - sum(r["seconds"] for r in rounds)
    print(f"train (first training, {rounds[0]['epochs']} epochs): {first_training:.0f} s; {_load()}")
    print("round | samples added (left out by the budget) / in all | database MB (uncompressed) | "
          "probes + certificate s | training s (epochs) | worst % (test) | tests not followed")
    for r in rounds:
        train_s = r["train_seconds"] if r["round"] else 0.0
        print(f"{r['round']} | {r['samples_added']} ({r.get('samples_capped', 0)}) / {r['samples_total']} | "
              f"{r.get('database_mb', float('nan')):.1f} ({r.get('database_raw_mb', float('nan')):.1f}) | "
              f"{r['seconds'] - train_s:.0f} | {train_s:.0f} ({r['epochs'] if r['round'] else '-'}) | "
              f"{100 * r['worst']:.3f} ({r['worst_test']}) | {', '.join(r.get('not_followed', [])) or '-'}")
    print(surrogate_line(Certificate.from_dict(meta["certificate"])))
    print(f"pipeline: {generated + trained:.0f} s ({(generated + trained) / 60:.1f} min), generate {generated:.0f} s, "
          f"train + certificate + rounds {trained:.0f} s; database {_mb(db)}; final verdict "
          f"{meta['certificate']['verdict']} (exit {code}); {_load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
