"""python studies/finegrain_first_guess.py --model M.pt [--shear 1e-5 1e-4 1e-3] [--cells 400] [--increments 12]:
how far the fine-grain hybrid's first guess is from balance, the network's against the previous increment repeated.

The cells of ``benchmarks/cells/fine_off_centre.toml`` (the model M trained on it), from rest through 20 isotropic
increments of 2e-5, then increments of a constant-volume-like shear S (``bench_backend_costs.py``'s path). At every
increment after the first, two first guesses of the free-DOF displacement, each with the rest rule and the
released-grain rule applied as the hybrid applies them: the network's (what the hybrid corrects) and the previous
increment's balanced displacement repeated. Prints, per increment, each guess's force ratio (largest unbalanced
free-DOF force over the largest normal force: largest and median over the cells) and the fraction of cells above the
certificate's tolerance R, where the hybrid takes a Newton correction. Uses ``FastAdvance``'s compiled kernels
directly (no Newton step is taken for the repeated guess: ``newton3d`` with 0 iterations only evaluates it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.files import load_mesostructure

ROOT = Path(__file__).resolve().parents[1]
FINE = ROOT / "benchmarks" / "cells" / "fine_off_centre.toml"


def repeated_ratio(model, state, shear: np.ndarray, previous: np.ndarray, resting: np.ndarray) -> np.ndarray:
    """Force ratio (n,) of the first guess ``previous`` (n_free, n) [m] from ``state``, after the hybrid's rules."""
    fast = model.fast
    before = fast._local.work.before  # the features of ``state``, left by the increment just taken from it
    size = np.ascontiguousarray(np.asarray(state.cell_size).T)
    free = np.ascontiguousarray(np.asarray(state.free_position).T)
    springs = np.ascontiguousarray(np.moveaxis(np.asarray(state.shear_force), 0, -1))
    d_free = np.ascontiguousarray(previous.copy())
    fast._hold(size, free, shear, d_free, fast.cells, fast.law, before)
    d_free[resting.T] = 0.0
    n = size.shape[1]
    ratios, counts = np.empty((2, n)), [np.empty(n, dtype=np.int64) for _ in range(3)]
    fast._newton(size, free, springs, np.ascontiguousarray(shear), d_free, fast.cells, fast.law, before, 0,
                 fast.tolerance, fast.halvings, fast.shift, ratios, *counts)
    return ratios[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--model", required=True, help="ANN model of fine_off_centre.toml (its default pipeline's)")
    parser.add_argument("--shear", type=float, nargs="+", default=[1e-5, 1e-4, 1e-3])
    parser.add_argument("--cells", type=int, default=400)
    parser.add_argument("--increments", type=int, default=12)
    args = parser.parse_args()
    if not Path(args.model).is_file():
        parser.error(f"--model {args.model}: no such file")
    if args.cells < 1 or args.increments < 2 or not all(0.0 < s < 1e-2 for s in args.shear):
        parser.error("--cells >= 1, --increments >= 2, each --shear in (0, 0.01)")
    meso = load_mesostructure(FINE)
    for strain in args.shear:
        model = make_cell_model("ann", dim=3, model=args.model, threads=1)
        n, tolerance = args.cells, model.fast.tolerance
        state = model.init_state(meso, n)
        for _ in range(20):
            state, _ = model.step(state, np.full((n, 3), 2e-5))
        shear = np.full((n, 3), -strain / 2)
        shear[:, 0] = strain
        previous = None
        for k in range(args.increments):
            resting = model._resting(state)
            model.fast.increment(*state, shear, False, held=resting)
            network = model.fast.last_corrections()[0][0].copy()
            if previous is not None:
                repeated = repeated_ratio(model, state, shear, previous, resting)
                print(f"S {strain:g} increment {k}: network max {network.max():.2e} median {np.median(network):.2e} "
                      f"above R {np.mean(network > tolerance):.2f} | previous repeated max {repeated.max():.2e} "
                      f"median {np.median(repeated):.2e} above R {np.mean(repeated > tolerance):.2f}", flush=True)
            new, _ = model.step(state, shear)
            previous = (np.asarray(new.free_position) - np.asarray(state.free_position)).T
            state = new


if __name__ == "__main__":
    main()
