"""python benchmarks/bench_ann.py [--model PATH] [--cells 360] [--repeats 2000]: ANN backend speed.

Prints, on one torch thread (torch.set_num_threads(1)):

1. the time of one network call and of one ``AnnCell.step`` for ``--cells`` cells
   (median over ``--repeats`` increments of a constant-volume-like load);
2. the wall time of the full constant-volume biaxial runs (alpha0 = 55 deg, isotropic
   compression to p0 = 5.85e6 N/m and, for static liquefaction, 2e5 N/m, then eps1 to 20 %
   in 1e-5 increments) through ``homogenization.driver`` with the ANN and with the
   analytical backend, with the largest deviation of p and q from the analytical curve as
   a fraction of p0, the q peaks and the final p.

The machine is shared: the load average (``os.getloadavg``) is printed with the numbers.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from homogenization import driver, loading
from homogenization.backends import make_cell_model
from homogenization.orientation import localise, orientations
from warp_hcell.parameters import CellDefaults


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=None, help="model state_dict (default: the shipped model)")
    parser.add_argument("--cells", type=int, default=360, help="cells (orientations) per increment")
    parser.add_argument("--repeats", type=int, default=2000, help="timed increments")
    parser.add_argument("--skip-run", action="store_true", help="only time single increments")
    parser.add_argument("--p0", type=float, nargs="+", default=[CellDefaults.p0, 2e5],
                        help="confining pressures of the constant-volume runs [N/m]")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; torch threads: {torch.get_num_threads()}")

    cell = make_cell_model("ann", model=args.model)
    orient = orientations(args.cells)
    state = cell.init_state(55.0, args.cells)
    iso = localise(orient, np.array([5e-6, 5e-6, 0.0]))
    for _ in range(200):
        state, _ = cell.step(state, iso)
    d_eps = localise(orient, np.array([1e-5, -1e-5, 0.0]))
    inputs = torch.from_numpy(np.column_stack([d_eps, np.degrees(state.alpha), state.N1, state.N2, state.T1,
                                               state.l1, state.l2]))
    with torch.inference_mode():
        net_ms = _median_ms(lambda: cell.net.predict(inputs), args.repeats)
    step_ms = _median_ms(lambda: cell.step(state, d_eps), args.repeats)
    print(f"{args.cells} cells: network call {net_ms:.3f} ms, AnnCell.step {step_ms:.3f} ms per increment (median)")
    if args.skip_run:
        return

    for p0 in args.p0:
        programme = loading.biaxial(p0, 0.2, 1e-5)
        records = {}
        for name, model in (("analytical", make_cell_model("analytical")), ("ann", cell)):
            start = time.perf_counter()
            records[name] = driver.run(model, programme, alpha0_deg=55.0, n_orientations=args.cells, progress=False)
            seconds = time.perf_counter() - start
            print(f"p0 = {p0:g}: {name} constant-volume run ({len(records[name].p)} increments) in {seconds:.1f} s "
                  f"({1e3 * seconds / len(records[name].p):.3f} ms per increment incl. the driver)")
        ref, ann = records["analytical"], records["ann"]
        a, b = ref.stage == "shear", ann.stage == "shear"
        n = min(a.sum(), b.sum())
        dp = np.max(np.abs(ann.p[b][:n] - ref.p[a][:n])) / p0
        dq = np.max(np.abs(ann.q[b][:n] - ref.q[a][:n])) / p0
        print(f"p0 = {p0:g}: shear stage max |p_ann - p_ana| / p0 = {dp:.4f}, max |q_ann - q_ana| / p0 = {dq:.4f}; "
              f"q peak ana {ref.q[a].max():.5g}, ann {ann.q[b].max():.5g} N/m "
              f"({100 * (ann.q[b].max() / ref.q[a].max() - 1):+.2f} %); final p ana {ref.p[a][-1]:.4g}, "
              f"ann {ann.p[b][-1]:.4g} N/m")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
