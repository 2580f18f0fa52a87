"""python studies/scan_dobrany_prediction_rules.py RESULT.json [RESULT.json ...] [--rules 15x4s,23x8s,...] [--tag T]
python studies/scan_dobrany_prediction_rules.py RESULT.json --vary NAME=V1,V2,... [--vary ...] --rules R [--tag T]

The three Dobrany tests at a calibration's posterior mean (a ``calibration_dobrany_product.py`` result JSON, every
setting of its command; ``sensitivity_setup``) on several orientation rules ORDERxSPINS[a|s] (Lebedev order, spins,
aligned or staggered), to see which rule the predicted test's numbers have converged on. Per result, rule and test:
RMS abs(dq) / q_peak of the data, RMS d eps_v, the strain at the highest q, the highest q, the plateau (the strain
range over which q stays within 1 % of its highest value, ``plateau``) and the wall time; the sand's highest q and
plateau beside. With ``--vary`` (a screen, no fit): every combination of the given values of the named forward
parameters (``forward.simulate``'s, e.g. e_gamma, kn, mobilisation_exponent), the rest the mean's, on the one rule,
ranked by the mean RMS abs(dq) / q_peak of the result's fitted tests. Writes
studies/results/scan_dobrany_prediction_rules_TAG.json and .txt.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import SPLITS  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, dobrany_tests, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402

PLATEAU = 0.01
"""Relative drop from the highest q [-] that bounds the plateau (``plateau``)."""


def plateau(eps1: np.ndarray, q: np.ndarray, drop: float = PLATEAU) -> tuple[float, float]:
    """(first, last) strain [-] of the points where q >= (1 - drop) max q, along the curve (eps1 (n,), q (n,))."""
    top = np.flatnonzero(q >= (1.0 - drop) * np.nanmax(q))
    return float(eps1[top[0]]), float(eps1[top[-1]])


def evaluate(result: Path, rule: str, grid: dict[str, list[float]], tests: dict) -> tuple[dict, dict]:
    """Every combination of ``grid``'s values (name -> values; empty: the mean alone) at ``result``'s mean on ``rule``,
    one batch per test: (the result's record, variant -> test name -> row of ``metrics``, the highest q, the plateau,
    the fallbacks and the batch's seconds)."""
    names = tuple(grid)
    variants = list(itertools.product(*grid.values()))
    record, params, settings = sensitivity_setup(result, rule, variants, names, kn_factor=None)
    rows: dict[tuple, dict] = {v: {} for v in variants}
    for name, test in tests.items():
        started = time.perf_counter()
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        seconds = time.perf_counter() - started
        for i, v in enumerate(variants):
            rows[v][name] = {"result": result.name, "rule": rule, "test": name, **dict(zip(names, v)),
                             **metrics(test, c.q[i], c.eps_v[i]), "q_max": float(np.nanmax(c.q[i])),
                             "plateau": list(plateau(test.eps1, c.q[i])), "fallbacks": int(c.n_fallback[i]),
                             "seconds": seconds}
    return record, rows


def screen(result: Path, rule: str, grid: dict[str, list[float]], tests: dict, rows: list[dict], say) -> None:
    """``evaluate`` of ``grid``: appends a row per variant and test to ``rows`` and says one line per variant, best
    first by the mean RMS abs(dq) / q_peak of the result's fitted tests."""
    record, by_variant = evaluate(result, rule, grid, tests)
    fitted, _ = SPLITS[record["split"]]
    rows.extend(r for by in by_variant.values() for r in by.values())
    say(f"== {result.name}, {rule}, variants by the mean RMS abs(dq)/q_peak of the fitted tests {', '.join(fitted)}")
    for v, by in sorted(by_variant.items(), key=lambda kv: np.mean([kv[1][n]["rms_dq_over_qpeak"] for n in fitted])):
        say(" ".join(f"{n} {x:g}" for n, x in zip(grid, v))
            + f": fitted {np.mean([by[n]['rms_dq_over_qpeak'] for n in fitted]):.4f} | " + " | ".join(
                f"{n[4:-4]}: dq {r['rms_dq_over_qpeak']:.3f}, dv {100 * r['rms_deps_v']:.2f} %, peak "
                f"{100 * r['eps1_at_peak_model']:.2f} % (1 %: {100 * r['plateau'][0]:.2f}-{100 * r['plateau'][1]:.2f}),"
                f" fb {r['fallbacks']}" for n, r in by.items()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, nargs="+")
    parser.add_argument("--rules", default="15x4s,23x8s,35x12s,35x16s,47x16s,59x24s")
    parser.add_argument("--vary", action="append", default=[], metavar="NAME=V1,V2,...",
                        help="a screen: these values of a forward parameter (repeatable; one result, one rule)")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    try:
        grid = {name: [float(v) for v in values.split(",")] for name, values in (g.split("=", 1) for g in args.vary)}
    except ValueError:
        print(f"error: --vary takes NAME=V1,V2,... (numbers); got {' '.join(args.vary)}", file=sys.stderr)
        return 2
    if grid and (len(args.results) != 1 or "," in args.rules):
        print("error: --vary screens one result on one rule (--rules R)", file=sys.stderr)
        return 2
    missing = [str(p) for p in args.results if not p.is_file()]
    if missing:
        print(f"error: no file {', '.join(missing)}", file=sys.stderr)
        return 2
    tests = dobrany_tests()
    lines: list[str] = []

    def say(line: str) -> None:
        lines.append(line)
        print(line, flush=True)

    for name, test in tests.items():
        a, b = plateau(test.eps1, test.observed["q"])
        at = 100 * test.eps1[np.argmax(test.observed["q"])]
        say(f"sand {name}: highest q {test.observed['q'].max() / 1e3:.0f} kPa at {at:.2f} %, within 1 % of it over "
            f"{100 * a:.2f}-{100 * b:.2f} %")
    rows = []
    if grid:
        screen(args.results[0], args.rules, grid, tests, rows, say)
    for result in args.results if not grid else ():
        say(f"== {result.name}")
        for rule in args.rules.split(","):
            by_test = evaluate(result, rule, {}, tests)[1][()]
            rows.extend(by_test.values())
            say(" | ".join([f"{rule:7s}"] + [
                f"{name[4:-4]}: dq {r['rms_dq_over_qpeak']:.3f}, dv {100 * r['rms_deps_v']:.2f} %, peak "
                f"{100 * r['eps1_at_peak_model']:.2f} % (1 %: {100 * r['plateau'][0]:.2f}-{100 * r['plateau'][1]:.2f}),"
                f" q {r['q_max'] / 1e3:.0f}, fb {r['fallbacks']}, {r['seconds']:.0f} s"
                for name, r in by_test.items()]))
    stem = f"scan_dobrany_prediction_rules_{args.tag}" if args.tag else "scan_dobrany_prediction_rules"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"results": [str(p) for p in args.results], "rows": rows},
                                                     indent=1))
    (RESULTS / f"{stem}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
