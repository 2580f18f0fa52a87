"""python studies/scan_dobrany_peak_strain.py RESULT.json [--rule 15x4s] [--tag T] [--only NAME,...] [--variants JSON]

One-at-a-time scan of where the Dobrany tests peak, at a calibration's posterior mean (a
``calibration_dobrany_product.py`` result JSON, its "mean" values, on its forward model, ``--rule``): each calibrated
parameter at two or three values (``PARAMETER_VALUES``; two of them also with e_Gamma moved so that e_c(100 kPa)
stays the mean's: ``LINE_PIVOTS``), and the fixed settings ``SETTING_VALUES`` (the critical-state rule's gain,
rate_gain and phases, the shear increment), one changed at a time. Per variant and test: RMS abs(dq) / q_peak,
RMS d eps_v, the strain at the first peak of q (``first_peak``), at the highest q and where q first reaches 95 % of
its highest, the sand's, and at the first peak the void ratio e over the variant's critical one e_c(p) at the point's
p = p0 + q / 3 (the interlocking factor's base, before the lag and the mobilisation). Then the variants in the
order of the 200 kPa test's first-peak strain. ``--only`` runs the listed variant groups (parameter or setting
names); ``--variants`` a JSON list of parameter changes (CLI name -> value) instead of the grid. The second,
swing-proof first peak needs a drop of 5 % (``DROP_WIDE``). Writes studies/results/scan_dobrany_peak_strain_TAG.json
(every row) and .txt (the printed lines).
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

from bench_real_sand_spread import metrics  # noqa: E402
from calibration_dobrany_product import RESULTS, data_copies, sensitivity_setup  # noqa: E402

from homogenization.calibration import forward  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.interlocking import P_REF, critical_void_ratio  # noqa: E402

DROP = 0.02
"""A first peak is a running maximum of q from which q falls by this share of it before exceeding it [-]."""
DROP_WIDE = 0.05
"""The same share for the second, swing-proof measure of the first peak [-]."""
REACH = 0.95
"""Share of the highest q whose first crossing is reported [-]."""
PARAMETER_VALUES = {
    "phi_g": (34.0, 42.0), "kn": ("x0.5", "x2"), "kt_over_kn": (1.0, 1.5), "e_min": (0.42, 0.47),
    "e_max": (0.66, 0.75), "alpha_c": (50.0, 56.0), "renewal_rate": ("x0.5", "x2"), "interlocking_m": (1.0, 3.0),
    "e_gamma": (0.62, 0.67), "lambda_c": (0.015, 0.06), "xi_c": (0.4, 1.0), "cell_spread": (0.1, 0.5),
    "mobilisation_strain": (0.0025, "x2", 0.02), "mobilisation_start": (0.3, 0.9),
    "mobilisation_void_slope": (0.0, 30.0)}
"""Values of each calibrated parameter (CLI units; "xF": F times the mean's)."""
LINE_PIVOTS = (0.015, 0.06)
"""lambda_c values also run with e_Gamma = e_c(100 kPa) + lambda_c (100 kPa / p_ref)^xi, the mean's e_c there."""
SETTING_VALUES = {"gain": (1.5, 6.0), "rate_gain": (0.7, 2.8), "phases": ("cell", "axis"), "increment": (1e-3, 4e-3)}
"""Values of the fixed settings (``CriticalState.gain``, ``rate_gain``, ``phases``; ``ForwardSettings.increment``)."""


def first_peak(q: np.ndarray, drop: float = DROP) -> int:
    """Index of the first running maximum of q (shape (n,)) from which q falls below (1 - drop) of it before it
    is exceeded; the index of the highest q where there is none."""
    top = 0
    for j in range(1, len(q)):
        if q[j] > q[top]:
            top = j
        elif q[j] < (1.0 - drop) * q[top]:
            return top
    return int(np.argmax(q))


def critical_void(values: dict[str, float], p: np.ndarray) -> np.ndarray:
    """e_c(p) [-] of a set's values (CLI names) at p [Pa] (``interlocking.critical_void_ratio``)."""
    return critical_void_ratio(p, values["e_gamma"], values["lambda_c"], values["xi_c"], P_REF)


def variants(mean: dict[str, float], only: set[str], given: list[dict] | None = None
             ) -> tuple[list[tuple[str, dict]], list[tuple[str, object]]]:
    """(parameter variants: (label, CLI name -> value), the mean first; setting variants: (name, value)); ``given``
    (CLI name -> value each) instead of the grid, with no setting variants."""
    out = [("mean", {})]
    if given is not None:
        return out + [(",".join(f"{k}={v:.4g}" for k, v in g.items()), g) for g in given if g], []
    for name, values in PARAMETER_VALUES.items():
        if only and name not in only:
            continue
        for v in values:
            value = mean[name] * float(v[1:]) if isinstance(v, str) else v
            out.append((f"{name}={value:.4g}", {name: value}))
    if not only or "lambda_c" in only:
        e_c100 = float(critical_void(mean, np.array(1e5)))
        for lam in LINE_PIVOTS:
            e_gamma = e_c100 + lam * (1e5 / P_REF) ** mean["xi_c"]
            out.append((f"lambda_c={lam:.4g},e_gamma={e_gamma:.4g}", {"lambda_c": lam, "e_gamma": e_gamma}))
    settings = [(k, v) for k, vs in SETTING_VALUES.items() if not only or k in only for v in vs]
    return out, settings


def row(label: str, name: str, test, values: dict[str, float], q: np.ndarray, eps_v: np.ndarray,
        fallbacks: int) -> dict:
    """One variant's numbers on one test (module docstring)."""
    e, q_data = test.eps1, test.observed["q"]
    m = metrics(test, q, eps_v)
    j = first_peak(q)
    p = test.p0 + q[j] / 3.0
    void = test.void_ratio - (1.0 + test.void_ratio) * eps_v[j]
    return {"variant": label, "test": name, "p0": test.p0,
            "e0": test.void_ratio, "rms_dq_over_qpeak": m["rms_dq_over_qpeak"], "rms_deps_v": m["rms_deps_v"],
            "first_peak_strain": float(e[j]), "first_peak_q": float(q[j]),
            "first_peak_wide_strain": float(e[first_peak(q, DROP_WIDE)]),
            "sand_first_peak_wide_strain": float(e[first_peak(q_data, DROP_WIDE)]),
            "highest_strain": float(e[np.argmax(q)]),
            "highest_q": float(q.max()), "reach_strain": float(e[np.argmax(q >= REACH * q.max())]),
            "sand_first_peak_strain": float(e[first_peak(q_data)]), "sand_highest_strain": float(e[np.argmax(q_data)]),
            "sand_reach_strain": float(e[np.argmax(q_data >= REACH * q_data.max())]),
            "void_over_critical_at_first_peak": float(void / critical_void(values, np.array(p))),
            "forward_fallbacks": fallbacks}


def line(r: dict) -> str:
    """One printed line of a row."""
    return (f"{r['variant']:>36s} {r['p0'] / 1e3:3.0f} kPa: dq {r['rms_dq_over_qpeak']:.3f}, deps_v "
            f"{100 * r['rms_deps_v']:.2f} %; first peak {r['first_peak_q'] / 1e3:4.0f} kPa at "
            f"{100 * r['first_peak_strain']:5.2f} % (sand {100 * r['sand_first_peak_strain']:.2f}), 5 %-drop peak at "
            f"{100 * r['first_peak_wide_strain']:5.2f} % (sand {100 * r['sand_first_peak_wide_strain']:.2f}), highest "
            f"{r['highest_q'] / 1e3:4.0f} at {100 * r['highest_strain']:5.2f} % "
            f"(sand {100 * r['sand_highest_strain']:.2f}),"
            f" 95 % at {100 * r['reach_strain']:5.2f} % (sand {100 * r['sand_reach_strain']:.2f}); e/e_c at first "
            f"peak {r['void_over_critical_at_first_peak']:.3f}; fallbacks {r['forward_fallbacks']}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path)
    parser.add_argument("--rule", default="15x4s")
    parser.add_argument("--tag", default="")
    parser.add_argument("--only", default="", help="comma-separated variant groups (parameter or setting names)")
    parser.add_argument("--variants", type=json.loads, default=None,
                        help='JSON list of {CLI name: value} instead of the grid, e.g. \'[{"cell_spread": 0.5}]\'')
    args = parser.parse_args(argv)
    only = {s for s in args.only.split(",") if s}
    unknown = only - set(PARAMETER_VALUES) - set(SETTING_VALUES)
    unknown |= {k for g in args.variants or [] for k in g} - set(PARAMETER_VALUES)
    if unknown or not args.result.is_file():
        print(f"error: unknown --only {sorted(unknown)} or no file {args.result}", file=sys.stderr)
        return 2
    record = json.loads(args.result.read_text())
    mean = record["mean"]["values"]
    par_variants, set_variants = variants(mean, only, args.variants)
    _, params, settings = sensitivity_setup(args.result, args.rule, [()] * len(par_variants), (), kn_factor=None)
    per_set = [dict(mean, **v) for _, v in par_variants]
    for name in {k for _, v in par_variants for k in v}:
        params[name] = np.array([s[name] for s in per_set])
    files = data_copies()
    rows, lines = [], []
    start = time.perf_counter()
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        runs = [(label, per_set[i], c.q[i], c.eps_v[i], int(c.n_fallback[i]))
                for i, (label, _) in enumerate(par_variants)]
        for key, value in set_variants:
            one = {k: v[:1] for k, v in params.items()}
            if key == "increment":
                s = replace(settings, increment=value)
            else:
                s = replace(settings, critical_state=replace(settings.critical_state, **{key: value}))
            with np.errstate(all="ignore"):
                c1 = forward.simulate(test, one, s)
            runs.append((f"{key}={value}", mean, c1.q[0], c1.eps_v[0], int(c1.n_fallback[0])))
        for label, values, q, eps_v, fb in runs:
            if len(q) != len(test.eps1):  # another increment: compare on the data's strains
                raise SystemExit(f"error: {label} returned {len(q)} points for {len(test.eps1)} strains")
            r = row(label, name, test, values, np.asarray(q), np.asarray(eps_v), fb)
            rows.append(r)
            lines.append(line(r))
            print(lines[-1], flush=True)
    lines.append(f"wall {time.perf_counter() - start:.0f} s; by the 200 kPa test's first-peak strain:")
    by = {}
    for r in rows:
        by.setdefault(r["variant"], {})[r["p0"]] = r
    for label, t in sorted(by.items(), key=lambda kv: -kv[1][200e3]["first_peak_strain"]):
        lines.append(f"{label:>36s}: first peak " + " / ".join(f"{100 * t[p]['first_peak_strain']:.2f}"
                                                               for p in sorted(t)) + " %; dq " +
                     " / ".join(f"{t[p]['rms_dq_over_qpeak']:.3f}" for p in sorted(t)))
    print("\n".join(lines[-len(by) - 1:]))
    stem = f"scan_dobrany_peak_strain_{args.tag or args.result.stem}"
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(args.result), "rule": args.rule,
                                                      "rows": rows}, indent=1))
    (RESULTS / f"{stem}.txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
