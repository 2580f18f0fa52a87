"""python studies/finegrain_release_rules.py (--models DIR --cells NAME | --model M.pt --mesostructure CELL) [--order 23 --spins 8] [--tests undrained drained]: the fine-grain hybrid under each released-grain rule against the DEM.

One model, one process: for each test (triaxial compression at ``--p0`` to ``--eps-max`` at ``--increment``, as
``benchmarks/bench_finegrain_hybrid.py`` runs it, after a short run of each that compiles its kernels) the DEM,
then the hybrid under each rule of ``homogenization.ann.escalation.RELEASE_RULES`` (``RELEASE_RULE_AFTER``: a
released grain found after the balance, its cell balanced again with it at rest; ``RELEASE_RULE``: the grains
nothing presses at the start also start at rest), interleaved, with the model's K and R. Prints per run its wall
time and the load, per rule the ratio to the DEM, the largest difference from the DEM over the path's scale
(``bench_finegrain_hybrid.difference``), Newton steps and cells corrected per increment, cell-increments released,
of them pushed, with a resting grain started at rest, left above R after K and handed to the DEM, and the
phases [s]. The model's certificate covers one of the two rules only: the other is measured, not certified.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    import bench_finegrain_hybrid as bench
    from warp_hcell.core.cli import Parser

    parser = Parser(description=__doc__.split("\n\n")[0])
    bench.add_cell_arguments(parser, one_cell=True, order=23, spins=8)
    parser.add_argument("--tests", nargs="+", choices=("undrained", "drained"), default=["undrained", "drained"])
    args = parser.parse_args(argv)
    args.equilibrium_corrections = args.equilibrium_tolerance = None
    (mesostructure, model_path), = bench.cells_of(args, parser)

    from homogenization.ann.escalation import RELEASE_RULE, RELEASE_RULE_AFTER
    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(mesostructure).build(None)
    dem = make_cell_model("dem", dim=3, threads=1)
    hybrids = {}
    for name, rule in (("earlier rule", RELEASE_RULE_AFTER), ("new rule", RELEASE_RULE)):
        timer = bench.PhaseTimer()
        model = bench.ann_model(model_path, timer)
        model.release_rule = rule
        hybrids[name] = (model, timer)
    first = hybrids["new rule"][0]
    certified = None if first.certificate is None else first.certificate.settings.get("dem_escalation_rule")
    print(f"{mesostructure}; model {model_path} (K = {first.equilibrium_corrections}, R = {first.force_tolerance:g}; "
          f"certificate's rule: {certified!r}); rule {args.order} x "
          f"{args.spins}; load average {os.getloadavg()}", flush=True)
    small = argparse.Namespace(**{**vars(args), "order": 3, "spins": 1})
    for model in (dem, *(m for m, _ in hybrids.values())):
        for test in args.tests:
            bench.run(model, meso, small, 10 * args.increment, test)
    for test in args.tests:
        records, walls = {}, {}
        for name in ("dem", *hybrids):
            model = dem if name == "dem" else hybrids[name][0]
            if name != "dem":
                hybrids[name][1].reset()
            records[name], walls[name] = bench.run(model, meso, args, args.eps_max, test)
            print(f"  {test} {name}: {walls[name]:.1f} s (load {os.getloadavg()[0]:.2f})", flush=True)
        for name, (_, timer) in hybrids.items():
            record = records[name]
            n = record.n_increments
            worst, scale = bench.difference(record, records["dem"], args.p0)
            count = {k: bench.total(record, f"n_{k}_all_calls") for k in
                     ("corrections", "corrected", "released", "released_pushed", "resting", "unconverged", "escalated")}
            print(f"{test}, {name}: hybrid {walls[name]:.1f} s / DEM {walls['dem']:.1f} s = {walls[name] / walls['dem']:.3f}; "
                  f"max |diff| / scale = {worst / scale:.2e} (scale {scale:.3g} Pa); {n} increments, "
                  f"{record.newton_iterations.sum():.0f} step calls; Newton corrections per increment "
                  f"{count['corrections'] / n:.0f}, cells corrected per increment {count['corrected'] / n:.0f}; "
                  f"cell-increments released {count['released']:.0f} (pushed {count['released_pushed']:.0f}), with a "
                  f"resting grain started at rest {count['resting']:.0f}, unconverged {count['unconverged']:.0f}, "
                  f"to the DEM {count['escalated']:.0f}", flush=True)
            print("  phases [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in timer.seconds.items()), flush=True)
    print(f"load average after: {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
