"""python studies/scan_dobrany_orientation_rules.py RESULT.json [--rules 11x4a,11x4s,...] [--reference 23x8s]

How far each 3D orientation rule's curves are from a fine rule's, at one optimum of the Dobrany interlocking fits
(a result of ``bench_real_sand_critical_state.py``, read by ``calibration_dobrany_product.start_point``; its
forward settings otherwise: shear increments 2e-3, isotropic 1e-3, kn (p0 / p_ref)^n with the result's n). A rule
ORDERxSPINS[a|s]: Lebedev order, spins, aligned (a) or staggered (s) spins (``ForwardSettings.staggered_spins``).
Prints per rule and test: cells per point, RMS abs(q - q_ref) / q_peak of the data, RMS abs(eps_v - eps_v_ref),
the strain at the highest q, and the wall time of the three tests (one set each). Output:
studies/results/scan_dobrany_orientation_rules_TAG.json (and the printout through tee).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import data_copies, start_point  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.interlocking import Interlocking  # noqa: E402
from homogenization.material.critical_state import DEFAULTS  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def settings_of(rule: str, n: float) -> forward.ForwardSettings:
    order, rest = rule.split("x")
    return forward.ForwardSettings(increment=2e-3, iso_increment=1e-3, stress_rtol=1e-5, critical_state=DEFAULTS[3],
                                   kn_exponent=n, interlocking=Interlocking(), lebedev_order=int(order),
                                   n_spins=int(rest[:-1]), staggered_spins=rest[-1] == "s")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--rules", default="11x4a,11x4s,11x8a,11x8s,17x4a,17x4s,13x4s,15x4s")
    parser.add_argument("--reference", default="23x8s")
    parser.add_argument("--tag", default="")
    args = parser.parse_args(argv)
    result = json.loads(args.result.read_text())
    values = dict(kv.split("=") for kv in start_point(args.result).split(","))
    params = {k: np.array([float(v)]) for k, v in values.items()}
    n = float(result.get("kn_exponent", 0.0))
    files = data_copies()
    tests = {name: read_test(path) for name, path in files.items()}
    out = {"result": str(args.result), "reference": args.reference, "rules": {}}
    curves = {}
    for rule in [args.reference] + args.rules.split(","):
        s = settings_of(rule, n)
        t0 = time.perf_counter()
        curves[rule] = {}
        for name, test in tests.items():
            with np.errstate(all="ignore"):
                c = forward.simulate(test, params, s)
            curves[rule][name] = (c.q[0], c.eps_v[0])
        seconds = time.perf_counter() - t0
        cells = forward.population({**{k: v for k, v in forward.full_parameters(params, s).items()}}, s, 3).material.orient.n_cells
        row = {"cells": int(cells), "seconds": seconds}
        for name, test in tests.items():
            q, ev = curves[rule][name]
            qr, evr = curves[args.reference][name]
            row[name] = {"rms_dq_ref_over_qpeak": float(np.sqrt(np.mean((q - qr) ** 2)) / test.observed["q"].max()),
                         "rms_deps_v_ref": float(np.sqrt(np.mean((ev - evr) ** 2))),
                         "eps1_at_peak": float(test.eps1[int(np.nanargmax(q))]),
                         "rms_dq_data_over_qpeak": float(np.sqrt(np.mean((q - test.observed["q"]) ** 2))
                                                         / test.observed["q"].max())}
        out["rules"][rule] = row
        print(f"{rule:7s} {cells:4d} cells {seconds:6.1f} s  " + "  ".join(
            f"{name.split('_')[1][:-7]}: dq/ref {row[name]['rms_dq_ref_over_qpeak']:.4f} dev/ref "
            f"{100 * row[name]['rms_deps_v_ref']:.3f} % peak {100 * row[name]['eps1_at_peak']:.2f} % "
            f"dq/data {row[name]['rms_dq_data_over_qpeak']:.3f}" for name in tests), flush=True)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"scan_dobrany_orientation_rules{'_' + args.tag if args.tag else ''}.json").write_text(
        json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
