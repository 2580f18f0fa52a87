"""python studies/diagnose_dobrany_q_error.py [--tag third_15x4s] [--sensitivity] [--kn-exponents 0.5,0.7]

Where along each Dobrany test the q error of the ``hmodel calibrate --interlocking`` posterior means on Lebedev
15 x 4 staggered spins lies (``studies/results/calibration_dobrany_product_SPLIT_third_15x4s.json``, written by
``calibration_dobrany_product.py``): per test and strain window (0-1 %, 1 % to the sand's peak, the peak to 10 %,
10-15 %, 15 % to the end) the RMS and the mean of (q_model - q_data) / q_peak and the window's share of the test's
squared error, at the mean on 15 x 4 staggered and on 23 x 8 staggered; then q model / data at a few strains.
``--tag``: another calibration of that script (its results ``..._SPLIT_TAG.json``).

``--sensitivity``: at each split's posterior mean (its calibration folder under runs/dobrany_product/), the
predicted test run with each calibrated parameter moved by +-10 % of its prior's width (log ones in log10; cut at the
prior's bounds) and, with
``--kn-exponents``, with kn's exponent changed (kn's value at 101.325 kPa held): per set the whole test's RMS
abs(dq) / q_peak, the 0-1 % window's and the peak-to-15 % window's, and the strain at the highest q; which
coordinate, moved at the predicted test's pressure alone, removes which part.
Writes studies/results/diagnose_dobrany_q_error[_sensitivity].txt (the printout).
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
from contextlib import redirect_stdout
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from calibration_dobrany_product import PRIOR, RUNS, data_copies  # noqa: E402

from homogenization.calibration import forward, posterior as post_mod  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "studies" / "results"
STRAINS = (0.1, 0.5, 1.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 15.0, 20.0)
"""Axial strains [%] of the q model / data rows."""


def windows(eps1_pct: np.ndarray, dq: np.ndarray, peak_pct: float) -> list[tuple[str, float, float, float]]:
    """(name, RMS, mean, share of the squared error) of dq over the module docstring's strain windows."""
    total = float(np.sum(dq ** 2))
    out = []
    for name, a, b in (("0-1%", 0.0, 1.0), ("1%-peak", 1.0, peak_pct), ("peak-10%", peak_pct, 10.0),
                       ("10-15%", 10.0, 15.0), ("15%-end", 15.0, math.inf)):
        m = (eps1_pct >= a) & (eps1_pct < b)
        out.append((name, float(np.sqrt(np.mean(dq[m] ** 2))), float(np.mean(dq[m])), float(np.sum(dq[m] ** 2)) / total))
    return out


def error_table(tag: str) -> None:
    for split in ("50+100", "50+200"):
        result = json.loads((RESULTS / f"calibration_dobrany_product_{split.replace('+', '_')}_{tag}.json")
                            .read_text())
        for label in ("mean", "mean_on_23x8s"):
            print(f"split {split}, posterior mean ({'15 x 4 s' if label == 'mean' else '23 x 8 s'}): window RMS / "
                  f"mean of (q_model - q_data) / q_peak [share of the squared error]")
            for name, c in result[label]["curves"].items():
                e, q, qd = 100 * np.asarray(c["eps1"]), np.asarray(c["q"]), np.asarray(c["q_data"])
                dq = (q - qd) / qd.max()
                role = result[label]["tests"][name]["role"]
                cells = "  ".join(f"{w} {r:.3f}/{m:+.3f} [{s:.2f}]" for w, r, m, s in windows(e, dq, e[np.argmax(qd)]))
                print(f"  {name:15s} {role:9s} all {np.sqrt(np.mean(dq ** 2)):.3f}  {cells}")
            print("  q model / data at eps1 [%]: " + " ".join(f"{s:g}" for s in STRAINS))
            for name, c in result[label]["curves"].items():
                e, q, qd = 100 * np.asarray(c["eps1"]), np.asarray(c["q"]), np.asarray(c["q_data"])
                idx = [int(np.argmin(abs(e - s))) for s in STRAINS]
                print(f"  {name:15s} " + " ".join(f"{q[i] / qd[i]:.2f}" for i in idx)
                      + "   data q [kPa] " + " ".join(f"{qd[i] / 1e3:.0f}" for i in idx))
            print()


def scores(test, q: np.ndarray) -> tuple[float, float, float, float]:
    """Whole-test RMS abs(dq) / q_peak, the 0-1 % window's, the peak-to-15 % window's, strain at the highest q [%]."""
    qd = test.observed["q"]
    e = 100 * test.eps1
    dq = (q - qd) / qd.max()
    peak = e[np.argmax(qd)]
    early, post = e < 1.0, (e >= peak) & (e < 15.0)
    return (float(np.sqrt(np.mean(dq ** 2))), float(np.sqrt(np.mean(dq[early] ** 2))),
            float(np.sqrt(np.mean(dq[post] ** 2))), float(e[np.nanargmax(q)]))


def sensitivity(kn_exponents: list[float]) -> None:
    files = data_copies()
    for split in ("50+100", "50+200"):
        _, predicted = SPLITS[split]
        post = post_mod.read_posterior(RUNS / f"{split.replace('+', '_')}_third_15x4s")
        mean = dict(post.mean)
        test = read_test(files[predicted])
        labels, sets = ["mean"], [dict(mean)]
        for name, bound in PRIOR.items():
            low, high, log = ((bound["low"], bound["high"], bound.get("log", False)) if isinstance(bound, dict)
                              else (bound[0], bound[1], False))
            for sign in (-1.0, 1.0):
                v = dict(mean)
                if log:
                    v[name] = mean[name] * 10.0 ** (sign * 0.1 * math.log10(high / low))
                else:
                    v[name] = min(max(mean[name] + sign * 0.1 * (high - low), low), high)
                labels.append(f"{name} {'-' if sign < 0 else '+'}10%")
                sets.append(v)
        params = {k: np.array([s[k] for s in sets]) for k in mean}
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, post.forward)
        rows = [(lab, *scores(test, c.q[i])) for i, lab in enumerate(labels)]
        for n in kn_exponents:
            with np.errstate(all="ignore"):
                cn = forward.simulate(test, {k: np.array([v]) for k, v in mean.items()},
                                      replace(post.forward, kn_exponent=n))
            rows.append((f"kn exponent {n:g}", *scores(test, cn.q[0])))
        print(f"split {split}: predicted {predicted} at the posterior mean (15 x 4 s), one coordinate moved by "
              f"+-10 % of its prior's width (kn's exponent {post.forward.kn_exponent:.4g} unless named)")
        print(f"  {'set':24s} {'RMS|dq|/q_pk':>12s} {'0-1%':>7s} {'pk-15%':>7s} {'eps1 at pk [%]':>14s}")
        for lab, rms, early, late, pk in rows:
            print(f"  {lab:24s} {rms:12.3f} {early:7.3f} {late:7.3f} {pk:14.2f}")
        print(f"  sand's strain at peak {100 * test.eps1[np.argmax(test.observed['q'])]:.2f} %")
        print()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tag", default="third_15x4s")
    parser.add_argument("--sensitivity", action="store_true")
    parser.add_argument("--kn-exponents", default="")
    args = parser.parse_args(argv)
    buffer = io.StringIO()
    with redirect_stdout(buffer):
        if args.sensitivity:
            sensitivity([float(x) for x in args.kn_exponents.split(",") if x])
        else:
            error_table(args.tag)
    sys.stdout.write(buffer.getvalue())
    stem = "diagnose_dobrany_q_error" + ("_sensitivity" if args.sensitivity else
                                         "" if args.tag == "third_15x4s" else f"_{args.tag}")
    (RESULTS / f"{stem}.txt").write_text(buffer.getvalue())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
