"""python studies/calibration_truth_resolution.py [--truths 0,1,2,3] [--out runs/calibration_truth_resolution]

Where the known truths of ``benchmarks/bench_calibrate_truths.py`` lie when each is fitted with forward
models of several resolutions: for each truth the same data (made as the benchmark makes them), a
least-squares fit (the maximum a posteriori under the flat prior, scipy's trust region from the truth)
with each (increment, orientations) of ``LEVELS``, and the Gauss-Newton posterior sd there. Prints per
level the optimum, (optimum - truth) / sd per parameter and chi-square: the finest levels show where
the noise alone puts the optimum, the coarse ones how far their discretisation moves it. Output:
studies/results/calibration_truth_resolution.txt (the printed table).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

from bench_calibrate_truths import TRUTHS, make_data  # noqa: E402

from homogenization.calibration import bayes  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.forward import ForwardSettings  # noqa: E402

LEVELS = ((1e-3, 36), (5e-4, 36), (5e-4, 72), (2.5e-4, 72), (2.5e-4, 144), (1.25e-4, 144), (1e-4, 72), (5e-5, 288),
          (2.5e-5, 288))
"""(increment and iso increment [-], orientations) of the fits: the default first, the data's source
(1e-4, 72) among them, the finest last."""
NAMES = ("phi_g", "alpha0")


def fit(tests: list, truth: np.ndarray, increment: float, orientations: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Optimum, Gauss-Newton sd and chi-square of ``tests`` with one forward-model resolution."""
    settings = ForwardSettings(n_orientations=orientations, increment=increment, iso_increment=increment, stress_rtol=1e-5)
    prior = bayes.make_prior(NAMES)
    post = bayes.Posterior(tests, prior, settings, 0.02)

    def residuals(x: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.nan_to_num(bayes.residuals(tests, post.curves(np.atleast_2d(x)), 0.02)[0], nan=1e3)

    result = least_squares(residuals, truth, diff_step=1e-5, bounds=(prior.low, prior.high))
    sd = np.sqrt(np.diag(np.linalg.pinv(result.jac.T @ result.jac)))
    return result.x, sd, 2.0 * result.cost


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truths", default=",".join(str(i) for i in range(len(TRUTHS))))
    parser.add_argument("--out", type=Path, default=Path("runs/calibration_truth_resolution"))
    args = parser.parse_args()
    for i in (int(k) for k in args.truths.split(",")):
        truth = TRUTHS[i]
        x0 = np.array([truth[n] for n in NAMES])
        paths = make_data(truth, args.out / f"truth_{i}")
        tests = [read_test(path) for path in paths]
        print(f"truth {i}: phi_g {x0[0]:g}, alpha0 {x0[1]:g} deg (data by the {truth['source']})", flush=True)
        for increment, orientations in LEVELS:
            started = time.process_time()
            x, sd, chi2 = fit(tests, x0, increment, orientations)
            z = (x - x0) / sd
            print(f"  increment {increment:<8g} {orientations:4d} orientations: optimum phi_g {x[0]:8.4f} alpha0 {x[1]:8.4f}; "
                  f"sd {sd[0]:.4g} {sd[1]:.4g}; (optimum - truth) / sd {z[0]:+6.2f} {z[1]:+6.2f}; chi-square {chi2:6.1f} "
                  f"({time.process_time() - started:.1f} s CPU)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
