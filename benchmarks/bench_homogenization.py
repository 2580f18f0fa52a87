"""python benchmarks/bench_homogenization.py [--backend analytical] [--orientations 360] [--increment 1e-5] [--eps-max 0.2]

Wall time of the constant-volume biaxial test (isotropic stage to p0 = 5.85e6 N/m, then
constant-volume shear to eps1 = --eps-max): the whole run, the shear stage alone, the bare
backend (the same number of ``step`` calls without the driver) and the driver overhead
per increment (the driver on a backend whose step costs nothing). Target for the analytical backend at 360 orientations and 1e-5: shear
stage < 10 s on one core. Prints the machine load, since timings on a shared machine are
noisy; take the best of --repeat runs.
"""

from __future__ import annotations

import argparse
import os
import time

from homogenization.element_test import driver, programme as programmes
from homogenization.cli.progress import stage_bars
from homogenization.material import orientation
from homogenization.backends import BACKENDS, make_cell_model
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import CellDefaults, LoadingDefaults


class NullCell:
    """A cell model whose step costs nothing (returns a fixed response): isolates the driver."""

    name = "null"

    def __init__(self, model, state) -> None:
        self.response_ = model.response(state)
        self.arrays = model.state_to_arrays(state)

    def init_state(self, mesostructure, n_cells):
        return None

    def step(self, state, d_eps_local):
        return state, self.response_

    def response(self, state):
        return self.response_

    def observables(self, state):
        return {}

    def state_to_arrays(self, state):
        return self.arrays


def best_time(fn, repeat: int) -> tuple[float, object]:
    best, result = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--backend", choices=tuple(BACKENDS), default="analytical")
    parser.add_argument("--orientations", type=int, default=CellDefaults.n_orientations)
    parser.add_argument("--increment", type=float, default=LoadingDefaults.increment)
    parser.add_argument("--eps-max", type=float, default=LoadingDefaults.eps_max)
    parser.add_argument("--alpha0", type=float, default=CellDefaults.alpha0_deg)
    parser.add_argument("--p0", type=float, default=CellDefaults.p0)
    parser.add_argument("--device", default="cpu", help="passed to dem and ann")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    options = {"device": args.device} if args.backend in ("dem", "ann") else {}
    model = make_cell_model(args.backend, **options)
    iso = (programmes.isotropic(args.p0),)
    programme = programmes.biaxial(args.p0, args.eps_max, args.increment)
    n_shear = programme[1].n_increments
    kw = dict(mesostructure=h_cell(args.alpha0), n_orientations=args.orientations, progress=False)

    iso_record = driver.run(model, iso, **kw)
    # the bare backend: the same shear step calls from the post-isotropic state, no driver
    state = model.state_from_arrays(iso_record.final_state)
    d_local = orientation.localise(orientation.orientations(args.orientations),
                                   [args.eps_max / n_shear, -args.eps_max / n_shear, 0.0])

    def bare():
        s = state
        for _ in range(n_shear):
            s, _ = model.step(s, d_local)

    null = NullCell(model, state)
    shear_only = programme[1:]

    # interleaved repeats, so that load changes on a shared machine hit every measurement alike
    t_iso = t_shear = t_full = t_bare = t_bar = t_null = float("inf")
    for _ in range(args.repeat):
        t, record = best_time(lambda: driver.run(model, programme, **kw), 1)
        t_full = min(t_full, t)
        t_iso, t_shear = min(t_iso, record.step_seconds[0]), min(t_shear, record.step_seconds[1])
        t_bare = min(t_bare, best_time(bare, 1)[0])
        t_bar = min(t_bar, best_time(lambda: driver.run(model, programme, **{**kw, "progress": stage_bars}), 1)[0])
        t_null = min(t_null, best_time(lambda: driver.run(null, shear_only, **kw), 1)[0])
    load = os.getloadavg()
    print(f"backend={args.backend} orientations={args.orientations} increment={args.increment:g} "
          f"eps_max={args.eps_max:g} alpha0={args.alpha0:g} p0={args.p0:g} (best of {args.repeat})")
    print(f"load average (1, 5, 15 min): {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} cpus")
    print(f"isotropic stage: {iso_record.n_increments} increments in {t_iso:.2f} s")
    print(f"whole test:      {record.n_increments} increments in {t_full:.2f} s "
          f"({t_bar:.2f} s with the progress bar)")
    print(f"shear stage:     {n_shear} increments in {t_shear:.2f} s ({1e6 * t_shear / n_shear:.1f} us/increment)")
    print(f"bare backend:    {n_shear} step calls in {t_bare:.2f} s ({1e6 * t_bare / n_shear:.1f} us/call)")
    print(f"driver overhead: {1e6 * t_null / n_shear:.1f} us/increment (driver on a zero-cost backend)")


if __name__ == "__main__":
    main()
