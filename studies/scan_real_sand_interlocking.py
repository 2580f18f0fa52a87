"""python studies/scan_real_sand_interlocking.py --split 50+200|50+100 --start NAME=VALUE,... [--m A,B] [--e-gamma A,B]
                                               [--lambda-c A,B]

A grid of the interlocking friction's m, e_Gamma and lambda (``calibration.interlocking``) about a least-squares
optimum of ``bench_real_sand_critical_state.py --void-ratio --rule-params alpha_c_deg,log10_rate`` (its other
coordinates fixed at ``--start``), every set run in one batch on the two fitted tests with that script's forward
model; prints the chi-square of each set on the fitted tests, best first (a start for ``--interlocking`` fits:
the fitted tests only, the predicted test is not run).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_real_sand_critical_state as bench  # noqa: E402
from bench_real_sand import SPLITS  # noqa: E402

from homogenization.calibration import bayes  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=tuple(SPLITS), required=True)
    parser.add_argument("--start", required=True, help="NAME=VALUE,... of the law, map and rule coordinates")
    parser.add_argument("--m", default="0.5,1,2,3")
    parser.add_argument("--e-gamma", default="0.65,0.7,0.8")
    parser.add_argument("--lambda-c", default="0.02,0.05,0.1")
    args = parser.parse_args(argv)
    names = ("alpha_c_deg", "log10_rate")
    given = dict(item.split("=") for item in args.start.split(",") if item)
    base = [float(given[c]) for c in bench.LAW_VOID + names]
    grid = list(itertools.product(*(tuple(float(v) for v in a.split(",")) for a in (args.m, args.e_gamma, args.lambda_c))))
    X = np.array([base + list(g) for g in grid])
    tests = [bench.load(f, True) for f in SPLITS[args.split][0]]
    started = time.perf_counter()
    curves = [bench.simulate(t, X, names, bench.SETTINGS, False, True)[0] for t in tests]
    r = bayes.residuals(tests, [{"q": c.q, "p": c.p, "eps_v": c.eps_v} for c in curves], bench.NOISE)
    chi2 = np.sum(np.where(np.isfinite(r), r, 1e3) ** 2, axis=1)
    print(f"split {args.split}, {len(grid)} sets at {args.start}: {time.perf_counter() - started:.0f} s, "
          f"nice {os.nice(0)}, load {os.getloadavg()[0]:.1f}")
    print("chi-square  m  e_gamma  lambda_c  (fitted tests)")
    for k in np.argsort(chi2):
        print(f"{chi2[k]:.4g}  {grid[k][0]:g}  {grid[k][1]:g}  {grid[k][2]:g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
