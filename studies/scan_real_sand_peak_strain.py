"""python studies/scan_real_sand_peak_strain.py RESULT.json [--step F] [--tag T]

What sets the strain at peak of the Dobrany fits with the interlocking friction, its cells' spread, xi and kn
(p0 / p_ref)^n fitted (``bench_real_sand_critical_state.py ... --interlocking --free-xi --cell-spread
--fit-kn-exponent``): at the optimum of RESULT.json each coordinate is moved by +-F of its bound's width (default
0.05, clipped to the bounds) and the three tests run, all sets as one batch per test, on the study's forward model.
Prints per coordinate and test the change of the smoothed strain at peak (``soft_peak_strain``) and of the strain
at the highest q, per unit of the coordinate's bound width (central difference), and the tests' values at the
optimum. Output: studies/results/real_sand_peak_strain_scan_SPLIT[_TAG].txt when run through tee, and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, SPLITS  # noqa: E402
from bench_real_sand_critical_state import (BOUNDS, RESULTS, SETTINGS, load, simulate,  # noqa: E402
                                            soft_peak_strain)
from homogenization.calibration.data import read_test  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--step", type=float, default=0.05, help="the move, a fraction of each bound's width")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    res = json.loads(args.result.read_text())
    optimum = res["optimum"]
    coords = list(optimum)
    if coords[-1] != "kn_exponent" or "cell_spread" not in coords or "xi_c" not in coords:
        print(f"{args.result}: not a fit with --interlocking --free-xi --cell-spread --fit-kn-exponent",
              file=sys.stderr)
        return 2
    x0 = np.array([optimum[c] for c in coords])
    width = np.array([BOUNDS[c][1] - BOUNDS[c][0] for c in coords])
    lo, hi = np.array([BOUNDS[c][0] for c in coords]), np.array([BOUNDS[c][1] for c in coords])
    X = [x0]
    for j in range(len(coords)):
        for sign in (1.0, -1.0):
            x = x0.copy()
            x[j] = np.clip(x0[j] + sign * args.step * width[j], lo[j], hi[j])
            X.append(x)
    X = np.array(X)
    names = tuple(res["rule_params"])
    settings = replace(SETTINGS, increment=res["settings"]["increment"], iso_increment=res["settings"]["iso_increment"])
    fitted, predicted = SPLITS[res["split"]]
    out = {"result": str(args.result), "step": args.step, "coords": coords, "tests": {}}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = load(name, True)
        c, _ = simulate(test, X[:, :-1], names, settings, False, True, psi=False, spread=True, xi=True,
                        kn_exponent=X[:, -1])
        soft = soft_peak_strain(test.eps1, c.q)
        arg = test.eps1[np.nanargmax(np.where(np.isfinite(c.q), c.q, -np.inf), axis=1)]
        rms = np.sqrt(np.mean((c.q - test.observed["q"]) ** 2, axis=1)) / test.observed["q"].max()
        dx = (X[1::2] - X[2::2])[np.arange(len(coords)), np.arange(len(coords))] / width
        out["tests"][name] = {
            "role": "predicted" if name == predicted else "fitted",
            "soft_peak": float(soft[0]), "argmax_peak": float(arg[0]), "rms_dq_over_qpeak": float(rms[0]),
            "d_soft_peak": ((soft[1::2] - soft[2::2]) / dx).tolist(),
            "d_argmax_peak": ((arg[1::2] - arg[2::2]) / dx).tolist(),
            "d_rms": ((rms[1::2] - rms[2::2]) / dx).tolist()}
        print(f"{name} ({out['tests'][name]['role']}): smoothed strain at peak {100 * soft[0]:.2f} % (data "
              f"{100 * soft_peak_strain(test.eps1, test.observed['q'])[0]:.2f} %), at the highest q "
              f"{100 * arg[0]:.2f} %, RMS abs(dq)/q_peak {rms[0]:.3f}", flush=True)
    print(f"\nper unit of each bound's width (central difference, +-{args.step:g} of it): change of the smoothed "
          f"strain at peak [% strain]; in brackets of the strain at the highest q [%]")
    print(f"{'coordinate':14s} " + " ".join(f"{n.split('_')[1]:>22s}" for n in out["tests"]))
    for j, c in enumerate(coords):
        print(f"{c:14s} " + " ".join(f"{100 * t['d_soft_peak'][j]:+10.2f} ({100 * t['d_argmax_peak'][j]:+8.2f})"
                                     for t in out["tests"].values()))
    stem = f"real_sand_peak_strain_scan_{res['split'].replace('+', '_')}" + (f"_{args.tag}" if args.tag else "")
    (RESULTS / f"{stem}.json").write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
