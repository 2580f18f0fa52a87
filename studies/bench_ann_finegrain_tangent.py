"""python studies/bench_ann_finegrain_tangent.py --model M.pt [--mesostructure CELL] [--order 11 --spins 4] [--test drained] [--repeats 1]: the fine-grain hybrid with its tangent from torch autograd and compiled, against the DEM.

One triaxial test (``benchmarks/bench_finegrain_hybrid.py``'s: p0 = 2e5 Pa, to ``--eps-max`` at 1e-4) of the
certified hybrid of ``M.pt`` run three ways in one process, interleaved ``--repeats`` times after a short run of
each that compiles its kernels: the DEM (one thread), the hybrid whose stress control takes the tangent from the
torch path (``AnnCell.step(with_tangent=True)`` without ``FastAdvance``'s compiled tangent, as before it
existed) and the hybrid with the compiled tangent (``training.fast_equilibrium3d.balance_tangent3d``). Prints
per run the wall time, then per variant the median, its ratio to the DEM's, the accuracy (largest difference of
sigma11, sigma22, sigma33, p and q over the shear stage over max(p0, largest DEM p)), step calls, tangent calls
and the cells of those calls that took no correction, and the load average.

``--one-call N``: instead, N cells of the cell (one orientation) compressed isotropically by 50 increments of
1e-4, then one step with a tangent of a drained probe (1e-4 axial, -5e-5 lateral), torch and compiled
interleaved ``--repeats`` times: each call's wall time and the largest difference of the two tangents over
the largest entry (all cells, and those corrected).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_finegrain_hybrid import FINE, TangentCount, ann_model, difference, run  # noqa: E402


class TorchTangent:
    """A hybrid whose tangent calls take the torch path: ``step(with_tangent=True)`` with its ``FastAdvance``
    set aside for that call (the cell model's own ``step`` otherwise)."""

    def __init__(self, model) -> None:
        self.model = model

    def __getattr__(self, name):
        return getattr(self.model, name)

    def step(self, state, d_eps_local, *, with_tangent: bool = False):
        if not with_tangent:
            return self.model.step(state, d_eps_local)
        fast, self.model.fast = self.model.fast, None
        try:
            new, response = self.model.step(state, d_eps_local, with_tangent=True)
        finally:
            self.model.fast = fast
        return new, response


def main(argv=None) -> int:
    from warp_hcell.core.cli import Parser, positive_float, positive_int

    parser = Parser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="a 3D meso-ANN model (.pt) of the cell, certified as the hybrid")
    parser.add_argument("--mesostructure", default=str(FINE), help="the cell (a file or a builder spec)")
    parser.add_argument("--p0", type=positive_float, default=2e5, help="isotropic pressure [Pa]")
    parser.add_argument("--eps-max", type=positive_float, default=0.05, help="axial strain of the shear stage [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--order", type=positive_int, default=11, help="Lebedev order of the cell axes")
    parser.add_argument("--spins", type=positive_int, default=4, help="spins per axis")
    parser.add_argument("--test", choices=("undrained", "drained"), default="drained")
    parser.add_argument("--repeats", type=positive_int, default=1, help="runs of each variant, interleaved")
    parser.add_argument("--one-call", type=positive_int, default=None, help="time one tangent call on this many cells")
    args = parser.parse_args(argv)
    if not Path(args.model).is_file():
        parser.error(f"--model {args.model}: no such file")
    if args.one_call:
        return one_call(args)

    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(args.mesostructure).build(None)
    compiled = ann_model(args.model, None)
    torch_path = ann_model(args.model, None)
    counts = {"torch tangent": TangentCount(torch_path), "compiled tangent": TangentCount(compiled)}
    variants = {"dem": make_cell_model("dem", dim=3, threads=1), "torch tangent": TorchTangent(torch_path),
                "compiled tangent": compiled}
    print(f"{args.mesostructure}; model {args.model} ({compiled.certificate_problem or 'certified'}); rule "
          f"{args.order} x {args.spins}; {args.test}; load average {os.getloadavg()}", flush=True)
    warm = argparse.Namespace(**{**vars(args), "order": 3, "spins": 1})
    for model in variants.values():
        run(model, meso, warm, 10 * args.increment, args.test)
    walls = {name: [] for name in variants}
    records = {}
    for _ in range(args.repeats):
        for name, model in variants.items():
            if name in counts:
                counts[name].reset()
            records[name], wall = run(model, meso, args, args.eps_max, args.test)
            walls[name].append(wall)
            print(f"  {name}: {wall:.1f} s (load {os.getloadavg()[0]:.2f})", flush=True)
    dem_s = statistics.median(walls["dem"])
    for name in ("torch tangent", "compiled tangent"):
        worst, scale = difference(records[name], records["dem"], args.p0)
        wall = statistics.median(walls[name])
        print(f"{name}: {wall:.1f} s, / DEM {wall / dem_s:.3f}; max |diff| / scale {worst / scale:.2e}; "
              f"{records[name].newton_iterations.sum():.0f} step calls, {counts[name].calls} with a tangent, "
              f"{counts[name].uncorrected} of their cell steps uncorrected", flush=True)
    print(f"DEM {dem_s:.1f} s; load average after: {os.getloadavg()}", flush=True)
    return 0


def one_call(args) -> int:
    """``--one-call``: one tangent call of ``args.one_call`` cells, torch and compiled (module docstring)."""
    import time

    import numpy as np

    from warp_hcell.mesostructures.builders import mesostructure_arg

    model = ann_model(args.model, None)
    torch_path = TorchTangent(model)
    n = args.one_call
    state = model.init_state(mesostructure_arg(args.mesostructure).build(None), n)
    for _ in range(50):
        state, _ = model.step(state, np.full((n, 3), 1e-4))
    probe = np.tile([1e-4, -0.5e-4, -0.5e-4], (n, 1))
    print(f"{args.mesostructure}; {n} cells; load average {os.getloadavg()}", flush=True)
    tangents = {}
    for k in range(args.repeats + 1):
        for name, variant in (("torch", torch_path), ("compiled", model)):
            start = time.perf_counter()
            _, response = variant.step(state, probe, with_tangent=True)
            wall = time.perf_counter() - start
            tangents[name] = response.tangent
            corrected = response.diagnostics["n_corrected"]
            print(f"  {name}{' (first: start-up)' if k == 0 else ''}: {wall:.2f} s; {corrected:.0f} of {n} cells "
                  f"corrected (load {os.getloadavg()[0]:.2f})", flush=True)
    scale = np.abs(tangents["torch"]).max()
    print(f"max |compiled - torch| / max |torch| = {np.abs(tangents['compiled'] - tangents['torch']).max() / scale:.2e}; "
          f"load average after: {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
