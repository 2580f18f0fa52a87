"""Cost of the ANN's run-time out-of-distribution checks: mean step time along a real path.

``python benchmarks/bench_ood.py [--cells 360] [--increments 2000] [--rounds 3]``

360 H-cells (alpha0 = 55 deg) compressed isotropically, then stepped along a constant-volume
path (each step from the state the previous one returned, so every ``OOD_INTERVAL``-th step
is checked, as in a run): the analytical backend, the ANN with its index (checks every
``homogenization.ann.ood.OOD_INTERVAL`` distinct states) and the same ANN with the checks
off, interleaved round by round. Prints the mean time per increment of each (a median would
hide the checked steps) and the time of one check.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.material.orientation import localise, orientations
from training.ood import state_features
from warp_hcell.mesostructures.hcell import h_cell


def _path_seconds(model, state, iso, d_eps, n: int) -> float:
    for _ in range(100):
        state, _ = model.step(state, iso)
    start = time.perf_counter()
    for _ in range(n):
        state, _ = model.step(state, d_eps)
    return (time.perf_counter() - start) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=360)
    parser.add_argument("--increments", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    print(f"load average (1, 5, 15 min): {os.getloadavg()}")
    orient = orientations(args.cells)
    iso = localise(orient, np.array([2e-5, 2e-5, 0.0]))
    d_eps = localise(orient, np.array([1e-4, -1e-4, 0.0]))
    with_ood = make_cell_model("ann", threads=1)
    without = make_cell_model("ann", threads=1)
    without.ood = None
    models = {"analytical": make_cell_model("analytical"), "ann with OOD": with_ood, "ann without OOD": without}
    meso = h_cell(55.0)
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.rounds + 1):  # the first round compiles and warms up, not counted
        for name, model in models.items():
            times[name].append(_path_seconds(model, model.init_state(meso, args.cells), iso, d_eps, args.increments))
    state = with_ood.init_state(meso, args.cells)
    features = state_features(with_ood.net, *state)
    check = np.median([(lambda t: (with_ood.ood.outside(features), time.perf_counter() - t)[1])(time.perf_counter())
                       for _ in range(50)])
    ms = {name: [1e3 * t for t in values[1:]] for name, values in times.items()}
    for name, values in ms.items():
        print(f"{name}: mean step {' / '.join(f'{v:.4f}' for v in values)} ms "
              f"(ratio to analytical {' / '.join(f'{v / a:.3f}' for v, a in zip(values, ms['analytical']))})")
    print(f"one check of {args.cells} cells (tree query): {1e3 * check:.2f} ms; checked "
          f"{int(with_ood.ood_counts[1])} cell-increments, {int(with_ood.ood_counts[0])} beyond the threshold")
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
