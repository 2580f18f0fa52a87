"""python benchmarks/bench_ann.py [--model PATH] [--cells 360] [--repeats 1000]: ANN vs analytical increment, side by side.

Prints, on one torch thread and in one run (the machine is shared: the load average is
printed with the numbers):

1. the median time of one ``step`` of ``--cells`` H-cells (alpha0 = 55 deg, after an
   isotropic compression, constant-volume-like increments of 1e-5) for the analytical and
   the ANN backend, interleaved, and their ratio; for the ANN also the network call alone
   (``MesoNet.displacement``) and the step with its autograd tangent;
2. unless ``--skip-run``: the constant-volume biaxial runs (isotropic compression to p0,
   then eps1 to 20 % in ``--increment`` steps) of both backends through
   ``homogenization.driver``, with the largest deviation of p and q from the analytical
   curve as a fraction of p0.
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


def _time(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=None, help="model state_dict (default: the shipped model)")
    parser.add_argument("--cells", type=int, default=360, help="cells (orientations) per increment")
    parser.add_argument("--repeats", type=int, default=1000, help="timed increments per backend")
    parser.add_argument("--skip-run", action="store_true", help="only time single increments")
    parser.add_argument("--increment", type=float, default=1e-5, help="shear increment of the runs [-]")
    parser.add_argument("--p0", type=float, nargs="+", default=[CellDefaults.p0, 2e5],
                        help="confining pressures of the constant-volume runs [N/m]")
    args = parser.parse_args()
    models = {"analytical": make_cell_model("analytical"), "ann": make_cell_model("ann", model=args.model, threads=1)}
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; torch threads: {torch.get_num_threads()}")

    orient = orientations(args.cells)
    iso = localise(orient, np.array([2e-5, 2e-5, 0.0]))
    d_eps = localise(orient, np.array([1e-5, -1e-5, 0.0]))
    states = {}
    for name, model in models.items():
        state = model.init_state(55.0, args.cells)
        for _ in range(100):
            state, _ = model.step(state, iso)
        states[name] = state
    times: dict[str, list[float]] = {"analytical": [], "ann": []}
    for _ in range(args.repeats):
        for name, model in models.items():
            times[name].append(_time(lambda: model.step(states[name], d_eps)))
    ann = models["ann"]
    tensors = [torch.from_numpy(a) for a in states["ann"]]
    d = torch.from_numpy(d_eps)
    with torch.inference_mode():
        net_ms = 1e3 * np.median([_time(lambda: ann.net.displacement(*tensors, d)) for _ in range(args.repeats)])
    tangent_ms = 1e3 * np.median([_time(lambda: ann.step(states["ann"], d_eps, with_tangent=True)) for _ in range(100)])
    ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    print(f"{args.cells} cells, median per increment: analytical step {ms['analytical']:.3f} ms, "
          f"ANN step {ms['ann']:.3f} ms (network call {net_ms:.3f} ms; with tangent {tangent_ms:.3f} ms); "
          f"ratio ANN / analytical = {ms['ann'] / ms['analytical']:.2f}")
    if args.skip_run:
        print(f"load average after: {os.getloadavg()}")
        return

    for p0 in args.p0:
        programme = loading.biaxial(p0, 0.2, args.increment, iso_increment=args.increment)
        records = {}
        for name, model in models.items():
            start = time.perf_counter()
            records[name] = driver.run(model, programme, alpha0_deg=55.0, n_orientations=args.cells, progress=False)
            seconds = time.perf_counter() - start
            print(f"p0 = {p0:g}: {name} constant-volume run ({len(records[name].p)} increments) in {seconds:.1f} s")
        ref, ann_run = records["analytical"], records["ann"]
        n = min(len(ref.p), len(ann_run.p))
        dp = np.max(np.abs(ann_run.p[:n] - ref.p[:n])) / p0
        dq = np.max(np.abs(ann_run.q[:n] - ref.q[:n])) / p0
        print(f"p0 = {p0:g}: max |p_ann - p_ana| / p0 = {dp:.4f}, max |q_ann - q_ana| / p0 = {dq:.4f}")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
