"""python studies/sensitivity_dobrany_decay.py RESULT.json [--rule 15x4s] [--tag T] [--grid G] [--tests LIST]
                                               [--fitted-first] [--lag softening_strain]

The interlocking's decay spread over a distortion growing with pressure (``calibration.interlocking``: the lag
``relax_strain`` gamma_r and its pressure exponent ``relax_exponent`` k, gamma_r(p) = gamma_r (p / p_ref)^k) at a
Dobrany calibration's posterior mean (a ``calibration_dobrany_product.py`` result; its mobilisation too, where it
has one): the three drained tests, one batch per test, for a grid of (gamma_r, k, kn factor, kn exponent), every
other parameter the mean's. ``--grid`` "G1,G2:K1,K2:F1,F2[:N1,N2]" replaces the default grid (N: kn's exponent,
per set; default the mean's or the settings'). Prints per variant and test RMS abs(dq) / q_peak, RMS d eps_v,
strain at the highest q (model, sand), q model / sand at 0.1 %, 1 % and 10 % of axial strain; ``--fitted-first``
then the variants in the order of the mean RMS abs(dq) / q_peak over the result's two fitted tests (a start chosen
from it does not see the predicted test). ``--lag softening_strain``: gamma is the lag since the point's densest
state (``softening_strain``) instead of ``relax_strain`` (the mean's relax_strain set to 0). Writes
studies/results/sensitivity_dobrany_decay_TAG.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, print_ranking, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402

GRID = {"gamma_r": (0.0, 0.01, 0.03), "k": (0.0, 1.0), "kn_factor": (1.0,), "n": (None,)}
"""The variants: gamma_r [-], k [-], kn factor [-], kn exponent [-] (gamma_r = 0: k is not read, so only one k;
None: the mean's exponent)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--rule", default="15x4s")
    parser.add_argument("--tag", default="")
    parser.add_argument("--grid", default="", help="G1,G2:K1,K2:F1,F2[:N1,N2] (gamma_r, k, kn factor, exponent)")
    parser.add_argument("--fitted-first", action="store_true", help="rank the variants by the fitted tests")
    parser.add_argument("--tests", default="cid_50kpa.csv,cid_100kpa.csv,cid_200kpa.csv")
    parser.add_argument("--lag", choices=("relax_strain", "softening_strain"), default="relax_strain")
    args = parser.parse_args(argv)
    grid = GRID
    if args.grid:
        grid = {**GRID, **dict(zip(GRID, ([float(x) for x in part.split(",")] for part in args.grid.split(":"))))}
    variants = [v for v in itertools.product(*grid.values()) if v[0] > 0.0 or v[1] == grid["k"][0]]
    record, params, settings = sensitivity_setup(args.result, args.rule, variants, (args.lag, "relax_exponent"))
    if args.lag == "softening_strain":
        params["relax_strain"] = np.zeros(len(variants))
    mean = record["mean"]["values"]
    if any(v[3] is not None for v in variants):
        default = mean.get("kn_exponent", settings.kn_exponent)
        params["kn_exponent"] = np.array([default if v[3] is None else v[3] for v in variants])
    files = data_copies()
    rows = []
    print(f"{args.result.name}: split {record['split']}, rule {args.rule}, load {os.getloadavg()[0]:.1f}", flush=True)
    for name in sorted((f for f in files if f in args.tests.split(",")), key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        started = time.perf_counter()
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        qd = test.observed["q"]
        for i, v in enumerate(variants):
            m = metrics(test, c.q[i], c.eps_v[i])
            ratio = [float(np.interp(e, test.eps1, c.q[i]) / np.interp(e, test.eps1, qd)) for e in (1e-3, 1e-2, 0.1)]
            rows.append({"test": name, "gamma_r": v[0], "k": v[1], "kn_factor": v[2], "n": v[3], **m,
                         "q_ratio_0.1%": ratio[0], "q_ratio_1%": ratio[1], "q_ratio_10%": ratio[2],
                         "fallbacks": int(c.n_fallback[i])})
            print(f"{name:15s} gamma_r {v[0]:5.3f} k {v[1]:.2f} kn x{v[2]:.1f} n {v[3]}: RMS dq/qpk "
                  f"{m['rms_dq_over_qpeak']:.3f} RMS deps_v {100 * m['rms_deps_v']:.2f} % peak "
                  f"{100 * m['eps1_at_peak_model']:.2f} / {100 * m['eps1_at_peak_data']:.2f} % q/sand at 0.1 % "
                  f"{ratio[0]:.2f}, 1 % {ratio[1]:.2f}, 10 % {ratio[2]:.2f}, fallbacks {int(c.n_fallback[i])}",
                  flush=True)
        print(f"  ({len(variants)} variants in {time.perf_counter() - started:.0f} s)", flush=True)
    if args.fitted_first:
        fitted = [n for n, t in record["mean"]["tests"].items() if t["role"] == "fitted"]
        print(f"variants by the mean RMS abs(dq)/q_peak over the fitted tests {', '.join(fitted)}:")
        print_ranking(rows, ("gamma_r", "k", "kn_factor", "n"), fitted,
                      lambda key: f"gamma_r {key[0]:5.3f} k {key[1]:.2f} kn x{key[2]:.1f} n {key[3]}")
    stem = f"sensitivity_dobrany_decay_{args.tag or record['split'].replace('+', '_')}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": args.rule,
                                                     "grid": grid, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
