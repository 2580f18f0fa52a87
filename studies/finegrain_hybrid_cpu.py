"""python studies/finegrain_hybrid_cpu.py (--models DIR --cells NAME | --model M.pt --mesostructure CELL) [--test undrained] [--order 53 --spins 16] [--eps-max 0.05]: the fine-grain hybrid's wall and CPU time alone.

One triaxial test of the certified hybrid (as ``benchmarks/bench_finegrain_hybrid.py`` runs it, after a short
run that compiles its kernels) in this process; prints the wall and process CPU seconds, the load and the last
q [Pa] in full (two checkouts that print the same q ran the same curve). Run it from two checkouts one after
the other, alternating, to compare their code: the CPU time is less sensitive to the load than the wall time.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    import bench_finegrain_hybrid as bench
    from warp_hcell.core.cli import Parser

    parser = Parser(description=__doc__.split("\n\n")[0])
    bench.add_cell_arguments(parser, one_cell=True, order=53, spins=16)
    parser.add_argument("--test", choices=("undrained", "drained"), default="undrained")
    args = parser.parse_args(argv)
    args.equilibrium_corrections = args.equilibrium_tolerance = None
    (mesostructure, model_path), = bench.cells_of(args, parser)

    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(mesostructure).build(None)
    ann = bench.ann_model(model_path, None)
    bench.run(ann, meso, argparse.Namespace(**{**vars(args), "order": 3, "spins": 1}), 10 * args.increment, args.test)
    start = time.process_time()
    record, wall = bench.run(ann, meso, args, args.eps_max, args.test)
    print(f"{Path(mesostructure).stem} {args.test} to {args.eps_max:g}, rule {args.order} x {args.spins}: wall {wall:.2f} s, "
          f"CPU {time.process_time() - start:.2f} s, load {os.getloadavg()[0]:.2f}, last q {float(record.q[-1])!r} Pa",
          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
