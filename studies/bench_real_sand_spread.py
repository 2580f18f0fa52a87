"""python studies/bench_real_sand_spread.py [--split 50+200|50+100] [--spread on|off] [--seed 3] [--out FILE.json]

Does a spread of initial opening angles (``alpha0_spread``, homogenization.material.opening_spread)
let the 3D H-model fit two drained triaxial tests of Dobrany sand and predict the third? The cheap
measure, no sampler: the least-squares optimum that ``hmodel calibrate --start map`` finds
(``homogenization.calibration.start.map_start``: 16 prior draws, the 3 best each start a bounded
least-squares fit on the likelihood's residuals) of phi_g, kn, kt/kn, alpha0 (--spread off) or
of those and alpha0_spread (--spread on), with the settings of studies/bench_real_sand.py
(Lebedev 11 x 4 aligned spins, shear increments of 2e-3, isotropic 1e-3, noise 2 %, kn prior
3e6-3e8 N/m, alpha0_spread prior [0, 10] deg cut by alpha0 - spread >= 45 deg); with --spread on
also one more fit started from the --spread off optimum (--from FILE.json of a --spread off run)
at a spread of 3 deg. ``--scan FILE.json`` instead runs the optimum of FILE (a --spread off result) with
alpha0_spread 0, 2, ..., 10 deg, the other parameters held, and prints each spread's chi-square on the
fitted tests and the misfits of all three (where the spread's evidence is one-dimensional), then
single-alpha0 points at the three families' opening angles of the largest spread scanned (each
family alone: its peak, where it comes, q and eps_v at the end). At the best optimum the calibration's forward model runs all three tests
and prints, per test, RMS |dq| / q_peak (measured peak), RMS d eps_v, peak q and the axial strain
at the peak (model / data), eps_v at the last measured eps1 (negative: dilated).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, PRIOR, SPLITS, print_prediction_table  # noqa: E402

from homogenization.calibration import bayes, start  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.forward import SPREAD, ForwardSettings, simulate  # noqa: E402
from homogenization.material import opening_spread  # noqa: E402

SETTINGS = ForwardSettings(increment=2e-3, iso_increment=1e-3, stress_rtol=1e-5)
"""The forward model of studies/bench_real_sand.py's calibrations (hmodel calibrate's defaults there)."""
NOISE = 0.02
PARAMS = ("phi_g", "kn", "kt_over_kn", "alpha0")


def metrics(test, q: np.ndarray, ev: np.ndarray) -> dict[str, float]:
    """Misfits of model curves at the data's eps1 (module docstring)."""
    qd, evd = test.observed["q"], test.observed["eps_v"]
    i_m, i_d = int(np.nanargmax(q)), int(np.argmax(qd))
    return {"p0": test.p0, "rms_dq_over_qpeak": float(np.sqrt(np.mean((q - qd) ** 2)) / qd.max()),
            "rms_deps_v": float(np.sqrt(np.mean((ev - evd) ** 2))),
            "q_peak_model": float(q[i_m]), "q_peak_data": float(qd[i_d]),
            "eps1_at_peak_model": float(test.eps1[i_m]), "eps1_at_peak_data": float(test.eps1[i_d]),
            "eps_v_end_model": float(ev[-1]), "eps_v_end_data": float(evd[-1])}


SCAN = np.arange(0.0, 10.5, 2.0)
"""Spreads of ``--scan`` [deg]."""


def scan(args: argparse.Namespace) -> int:
    """``--scan`` (module docstring): one batch of the spreads ``SCAN`` per test."""
    fitted, predicted = SPLITS[args.split]
    base = json.loads(args.scan.read_text())["optimum"]
    spreads = SCAN[opening_spread.feasible(base["alpha0"], SCAN)]  # alpha0 - spread >= 45 deg
    params = {**{k: np.full(spreads.size, v) for k, v in base.items()}, SPREAD: spreads}
    rows = {}
    chi2 = np.zeros(spreads.size)
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = read_test(DATA / name)
        with np.errstate(all="ignore"):
            c = simulate(test, params, SETTINGS)
        if name in fitted:
            chi2 += np.sum(bayes.residuals([test], [{"q": c.q, "p": c.p, "eps_v": c.eps_v}], NOISE) ** 2, axis=1)
        rows[name] = [{"spread": float(s), "forward_fallbacks": int(c.n_fallback[i]), **metrics(test, c.q[i], c.eps_v[i])}
                      for i, s in enumerate(spreads)]
    out = {"split": args.split, "at": base, "spreads": spreads.tolist(), "chi_square_fitted": chi2.tolist(), "tests": rows,
           "load_average_at_end": list(os.getloadavg())}
    if args.out is not None:
        args.out.write_text(json.dumps(out, indent=2) + "\n")
    x, _ = opening_spread.nodes()
    single = {**{k: np.full(x.size, v) for k, v in base.items()}, "alpha0": base["alpha0"] + spreads[-1] * x}
    families = {}
    for name in rows:
        test = read_test(DATA / name)
        with np.errstate(all="ignore"):
            c = simulate(test, single, SETTINGS)
        families[name] = [{"alpha0": float(a), **metrics(test, c.q[i], c.eps_v[i]), "q_end": float(c.q[i, -1])}
                          for i, a in enumerate(single["alpha0"])]
    out["families_alone"] = {"spread": float(spreads[-1]), "tests": families}
    if args.out is not None:
        args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"split {args.split}: spread scan at " + ", ".join(f"{k} {v:.4g}" for k, v in base.items()))
    print("spread [deg]  chi2 fitted  " + "  ".join(f"{n.split('_')[1].removesuffix('kpa.csv'):>3s} kPa: RMS dq/q_pk, d eps_v, q_pk [kPa], "
                                                  f"eps1 pk [%], eps_v end [%]" for n in rows))
    for i, s in enumerate(spreads):
        cells = []
        for name, r in rows.items():
            m = r[i]
            cells.append(f"{m['rms_dq_over_qpeak']:.3f}, {100 * m['rms_deps_v']:.2f} %, {m['q_peak_model'] / 1e3:.0f}, "
                         f"{100 * m['eps1_at_peak_model']:.1f}, {100 * m['eps_v_end_model']:.2f} ({m['forward_fallbacks']})")
        print(f"{s:6.1f}  {chi2[i]:12.4g}   " + "   |   ".join(cells))
    print(f"each family of spread {spreads[-1]:g} deg alone (single alpha0): q_pk [kPa] at eps1 [%], q end [kPa], "
          f"eps_v end [%]")
    for name, fams in families.items():
        print(f"  {name}: " + "; ".join(f"alpha0 {f['alpha0']:.1f}: {f['q_peak_model'] / 1e3:.0f} at "
                                        f"{100 * f['eps1_at_peak_model']:.1f}, {f['q_end'] / 1e3:.0f}, "
                                        f"{100 * f['eps_v_end_model']:.1f}" for f in fams))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1])
    parser.add_argument("--split", choices=tuple(SPLITS), default="50+200")
    parser.add_argument("--spread", choices=("on", "off"), default="on")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--from", dest="start_from", type=Path, default=None,
                        help="--spread on: a --spread off result (JSON) whose optimum starts one more fit")
    parser.add_argument("--scan", type=Path, default=None, help="a --spread off result (JSON): scan the spread at its optimum")
    parser.add_argument("--out", type=Path, default=None, help="result JSON")
    args = parser.parse_args(argv)
    if args.scan is not None:
        return scan(args)
    fitted, predicted = SPLITS[args.split]
    tests = [read_test(DATA / f) for f in fitted]
    names = PARAMS + ((SPREAD,) if args.spread == "on" else ())
    prior = bayes.make_prior(names, None, dim=3)
    prior = bayes.Prior(prior.names, np.where(np.array(names) == "kn", PRIOR["kn"][0], prior.low),
                        np.where(np.array(names) == "kn", PRIOR["kn"][1], prior.high), prior.log)
    log_post = bayes.Posterior(tests, prior, SETTINGS, NOISE)
    started = time.perf_counter()
    _, record = start.map_start(log_post, 2 * len(names), np.random.default_rng(args.seed))
    best = dict(record["optimum"])
    if args.start_from is not None and args.spread == "on":
        base = json.loads(args.start_from.read_text())["optimum"]
        x0_values = np.array([base[n] for n in PARAMS] + [3.0])
        x0_values[3] = max(x0_values[3], 45.0 + 3.0 + 1e-6)
        res = start.Residuals(log_post)
        chi2, fit = start.least_squares_fit(res, prior.to_coord(x0_values), prior.lo_coord, prior.hi_coord,
                                            log_post.feasible)
        record["from_spread_off_optimum"] = {"chi_square": chi2, "status": int(fit.status), "evaluations": res.evaluations,
                                             "optimum": {n: float(v) for n, v in zip(names, prior.to_values(fit.x))}}
        if chi2 < record["chi_square"]:
            best = record["from_spread_off_optimum"]["optimum"]
    seconds = time.perf_counter() - started
    results = {}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = read_test(DATA / name)
        with np.errstate(all="ignore"):
            c = simulate(test, {k: np.array([v]) for k, v in best.items()}, SETTINGS)
        results[name] = {"role": "predicted" if name == predicted else "fitted", "forward_fallbacks": int(c.n_fallback[0]),
                         **metrics(test, c.q[0], c.eps_v[0])}
    out = {"split": args.split, "spread": args.spread, "seed": args.seed, "optimum": best, "start": record,
           "seconds": seconds, "load_average_at_end": list(os.getloadavg()), "tests": results}
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"split {args.split}, spread {args.spread}: optimum " + ", ".join(f"{k} {v:.4g}" for k, v in best.items())
          + f"; chi-square {record['chi_square']:.4g} over {record['residuals']} residuals (map start)"
          + (f", {record['from_spread_off_optimum']['chi_square']:.4g} from the spread-off optimum"
             if "from_spread_off_optimum" in record else "")
          + f"; {record['evaluations']} sets, {seconds:.0f} s, load {os.getloadavg()[0]:.1f}")
    for fit in record["fits"]:
        print(f"  fit: chi-square {fit['chi_square']:.4g} at " + ", ".join(f"{k} {v:.4g}" for k, v in fit["optimum"].items()))
    print_prediction_table(results, fallbacks=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
