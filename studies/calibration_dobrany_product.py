"""python studies/calibration_dobrany_product.py --split 50+100|50+200 --tag T [--steps N] [--start-from JSON]
                                                [--extra "FLAGS"] [--evaluate-only] [--check-rule 23x8s]
                                                [--fit-kn-exponent] [--fit-mobilisation A,R0 [--kn-factor F]]
                                                [--fit-decay G,K [--kn-factor F]] [--fit-softening G,K]
                                                [--fit-void-lag G,K,S|G,S] [--fit-mobilisation-void A,R0,S]
                                                [--fit-state-map W [--state-map-prior LOW,HIGH]]
                                                [--fit-stiffness-void S [--kn-factor F]]
       python studies/calibration_dobrany_product.py --splits-figure OUT.png RESULT.json[+RESULT2.json] ...

Dobrany sand with the product's own ``hmodel calibrate``: the interlocking friction (``--interlocking``: m,
e_gamma, lambda_c, xi_c and the cells' spread calibrated), the critical-state renewal (alpha_c, renewal_rate),
the void-ratio map (e_min, e_max; each data file carries its specimen's void ratio at the start of shear), phi_g,
kn (its value at 101.325 kPa; ``--kn-exponent``, default 1/3) and kt/kn: 13 parameters, the configuration of
the interlocking and peak-strain studies (docs/studies/calibration_dobrany_interlocking.md), on the forward
model they used (Lebedev 11 x 4 aligned spins, shear increments 2e-3, isotropic 1e-3, drained Newton to 1e-5,
noise 2 %, the studies' bounds as the prior: ``PRIOR``). The walkers start around one least-squares fit from
``--start-from`` (a study optimum, fitted on the same two tests; ``--start-point``). The predicted test never
enters the calibration. Then all three tests at the posterior mean (what ``hmodel triaxial --posterior``
replays) and at the start's least-squares optimum: RMS abs(dq) / q_peak, RMS d eps_v, strain at the highest q;
``--check-rule`` also at the mean on another orientation rule (ORDERxSPINS, a: aligned, s: staggered spins), e.g.
23x8s, within about 1 % of q_peak of 35 x 8 (``scan_dobrany_orientation_rules.py``). ``--fit-kn-exponent``
calibrates kn's exponent too (``--params ...,kn_exponent``, prior [0, 1], started at ``--kn-exponent``); a
``--start-from`` JSON written by this script starts from its start's least-squares optimum ("optimum" "values").
``--fit-mobilisation A,R0`` calibrates the interlocking friction's mobilisation too (``mobilisation_strain``,
``mobilisation_start``; prior [0, 0.03] and [0, 1]), started at A and R0, kn started at ``--kn-factor`` times the
start's (the mobilisation softens the first percent, which a stiffer contact restores). ``--fit-decay G,K``
calibrates the interlocking's lag and its pressure exponent (``relax_strain``, ``relax_exponent``; prior [0, 0.1]
and [0, 2]), started at G and K, kn at ``--kn-factor`` times the start's. ``--fit-softening G,K`` the same with the
softening since the point's densest state (``softening_strain``, prior [0, 0.1]) instead of the lag. ``--fit-void-lag
G,K,S`` calibrates the lag with its void-ratio factor (``relax_strain``, ``relax_exponent``, ``relax_void_slope``;
prior [0, 0.1], [0, 2], [0, 40]), started at G, K and S; ``--fit-void-lag G,S``: relax_exponent not calibrated (0).
``--fit-mobilisation-void A,R0,S`` calibrates the mobilisation with its void-ratio factor (``mobilisation_strain``,
``mobilisation_start``, ``mobilisation_void_slope``; prior [0, 0.03], [0, 1], [0, 40]), started at A, R0 and S, kn at
``--kn-factor`` times the start's; its pressure exponent stays at the flags' (``--extra "--interlocking-values
mobilisation_exponent=N"``; default 2/3). ``--fit-state-map W`` calibrates the interlocking's state-map weight too
(``map_state_weight``: each test's cell at the map's alpha0 of e0 + w lambda_c ((p0 / p_ref)^xi_c - 1); prior [0, 2],
or ``--state-map-prior``'s), started at W. ``--fit-stiffness-void S`` calibrates the interlocking's stiffness slope too
(``stiffness_void_slope``: each test's kn times exp(-s_k (e0 - 0.55)); prior [0, 30]), started at S, kn at
``--kn-factor`` times the start's.

Writes the data copies, the prior and the calibration under runs/dobrany_product/ (ignored), and
studies/results/calibration_dobrany_product_SPLIT_TAG.json and .png (q and eps_v, data and the mean's curves).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, SPLITS, print_prediction_table  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402

from homogenization.calibration import forward, posterior as post_mod  # noqa: E402
from homogenization.calibration.data import read_test  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "studies" / "results"
RUNS = ROOT / "runs" / "dobrany_product"
PARAMS = ("phi_g", "kn", "kt_over_kn", "e_min", "e_max", "alpha_c", "renewal_rate", "interlocking_m", "e_gamma",
          "lambda_c", "xi_c", "cell_spread")
"""The calibrated parameters (12; with kn_exponent fixed)."""
PRIOR = {"phi_g": [10.0, 45.0], "kn": {"low": 3e6, "high": 3e8, "log": True}, "kt_over_kn": [0.1, 1.5],
         "e_min": [0.2, 0.52], "e_max": [0.59, 1.2], "alpha_c": [46.0, 62.0],
         "renewal_rate": {"low": 1.0, "high": 1000.0, "log": True}, "interlocking_m": [0.0, 6.0],
         "e_gamma": [0.5, 1.2], "lambda_c": [0.0, 0.4], "xi_c": [0.2, 1.0], "cell_spread": [0.0, 0.6]}
"""The studies' bounds (``bench_real_sand_critical_state.BOUNDS``) in CLI units."""
MOBILISATION = ("mobilisation_strain", "mobilisation_start")
"""The mobilisation's parameters (``--fit-mobilisation``)."""
MOBILISATION_PRIOR = {"mobilisation_strain": [0.0, 0.03], "mobilisation_start": [0.0, 1.0]}
"""Their bounds in the study's prior [-]."""
DECAY = ("relax_strain", "relax_exponent")
"""The lag's parameters (``--fit-decay``)."""
DECAY_PRIOR = {"relax_strain": [0.0, 0.1], "relax_exponent": [0.0, 2.0]}
"""Their bounds in the study's prior [-]."""
SOFTENING = ("softening_strain", "relax_exponent")
"""The softening's parameters (``--fit-softening``)."""
SOFTENING_PRIOR = {"softening_strain": [0.0, 0.1], "relax_exponent": [0.0, 2.0]}
"""Their bounds in the study's prior [-]."""
VOID_LAG = (*DECAY, "relax_void_slope")
"""The lag's parameters with its void-ratio factor (``--fit-void-lag``)."""
VOID_LAG_PRIOR = {**DECAY_PRIOR, "relax_void_slope": [0.0, 40.0]}
"""Their bounds in the study's prior [-]."""
MOBILISATION_VOID = (*MOBILISATION, "mobilisation_void_slope")
"""The mobilisation's parameters with its void-ratio factor (``--fit-mobilisation-void``)."""
MOBILISATION_VOID_PRIOR = {**MOBILISATION_PRIOR, "mobilisation_void_slope": [0.0, 40.0]}
"""Their bounds in the study's prior [-]."""
STATE_MAP_PRIOR = {"map_state_weight": [0.0, 2.0]}
"""The state-map weight's bounds in the study's prior [-] (``--fit-state-map``)."""
STIFFNESS_VOID_PRIOR = {"stiffness_void_slope": [0.0, 30.0]}
"""The stiffness slope's bounds in the study's prior [-] (``--fit-stiffness-void``)."""
STUDY = {"phi_g": "phi_g", "log10_kn": "kn", "kt_over_kn": "kt_over_kn", "e_min": "e_min", "e_max": "e_max",
         "alpha_c_deg": "alpha_c", "log10_rate": "renewal_rate", "interlocking_m": "interlocking_m",
         "e_gamma": "e_gamma", "lambda_c": "lambda_c", "xi_c": "xi_c", "cell_spread": "cell_spread"}
"""A study optimum's coordinate -> the CLI parameter (log10 ones raised)."""
FLAGS = ["--backend", "analytical", "--critical-state", "--interlocking", "--increment", "2e-3", "--iso-increment",
         "1e-3", "--stress-rtol", "1e-5", "--confirm", "none", "--resolution", "off", "--walkers", "26"]


def data_copies() -> dict[str, Path]:
    """Each Dobrany test as a calibration CSV with '# void_ratio = E' (its specimen's, at the start of shear)."""
    folder = RUNS / "data"
    folder.mkdir(parents=True, exist_ok=True)
    specimens = json.loads((DATA / "specimens.json").read_text())["tests"]
    out = {}
    for name in ("cid_50kpa.csv", "cid_100kpa.csv", "cid_200kpa.csv"):
        e = next(float(t["void_ratio_start_of_shear"]) for t in specimens if t.get("file") == name)
        lines = (DATA / name).read_text().splitlines()
        at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
        (folder / name).write_text("\n".join(lines[:at] + [f"# void_ratio = {e!r}"] + lines[at:]) + "\n")
        out[name] = folder / name
    return out


def dobrany_tests() -> dict:
    """Each Dobrany test (``data_copies``) read as a ``Measurement``, keyed by file name, in order of p0."""
    files = data_copies()
    tests = {name: read_test(path) for name, path in files.items()}
    return dict(sorted(tests.items(), key=lambda item: item[1].p0))


def sensitivity_setup(result: Path, rule: str, variants: list[tuple], names: tuple[str, ...], kn_factor: int | None = 2
                      ) -> tuple[dict, dict[str, np.ndarray], forward.ForwardSettings]:
    """For a sensitivity grid around a study result (``result``, its JSON): (the record, the forward model's
    per-variant parameters, its settings on ``rule``, e.g. "15x4s"): the posterior mean's values, the parameters
    ``names`` from each variant's first values, kn times its value at index ``kn_factor`` (None: kn the mean's)."""
    from homogenization.calibration.interlocking import Interlocking  # noqa: PLC0415

    record = json.loads(result.read_text())
    mean = record["mean"]["values"]
    out = RUNS / f"{record['split'].replace('+', '_')}_{record['tag']}"
    if (out / "posterior.json").is_file():
        settings = post_mod.read_posterior(out).forward
    else:  # the calibration's folder is not kept: its settings from its command's flags
        from homogenization.cli import calibrate  # noqa: PLC0415

        flags = shlex.split(record["command"])[3:]
        settings = calibrate.forward_settings(calibrate.build_parser().parse_args(flags), 3)
    order, rest = rule.split("x")
    settings = replace(settings, lebedev_order=int(order), n_spins=int(rest[:-1]), staggered_spins=rest[-1] == "s",
                       interlocking=settings.interlocking or Interlocking())
    params = {k: np.full(len(variants), float(v)) for k, v in mean.items()}
    if kn_factor is not None:
        params["kn"] = params["kn"] * np.array([v[kn_factor] for v in variants])
    for k, name in enumerate(names):
        params[name] = np.array([v[k] for v in variants])
    return record, params, settings


def print_ranking(rows: list[dict], keys: tuple[str, ...], fitted: list[str], label: Callable[[tuple], str]) -> None:
    """The variants of a sensitivity grid (``rows``: one per variant and test, with "test" and ``metrics``' fields)
    in the order of their mean RMS abs(dq) / q_peak over the ``fitted`` tests, one line each: ``label`` of the
    variant's values of ``keys``, that mean, then each test's RMS abs(dq) / q_peak, RMS d eps_v and peak strains."""
    score: dict[tuple, dict] = {}
    for r in rows:
        score.setdefault(tuple(r[k] for k in keys), {})[r["test"]] = r
    for key, by_test in sorted(score.items(), key=lambda kv: np.mean([kv[1][n]["rms_dq_over_qpeak"] for n in fitted])):
        print(f"  {label(key)}: fitted {np.mean([by_test[n]['rms_dq_over_qpeak'] for n in fitted]):.4f}; " + "; ".join(
            f"{n} {t['rms_dq_over_qpeak']:.3f}, {100 * t['rms_deps_v']:.2f} %, peak "
            f"{100 * t['eps1_at_peak_model']:.2f}/{100 * t['eps1_at_peak_data']:.2f} %" for n, t in by_test.items()))


def grid_scan(result: Path, names: tuple[str, ...], keys: tuple[str, ...], formats: tuple[str, ...],
              grid: list[list[float]], stem: str) -> None:
    """A sensitivity grid at a study result's posterior mean (``sensitivity_setup`` on 15 x 4 staggered, kn the mean's):
    the parameters ``names`` over every combination of ``grid``'s values, the three drained tests one batch each.
    Prints per variant and test RMS abs(dq) / q_peak, RMS d eps_v, the strain at the highest q (model / sand) and the
    forward fallbacks, each value as ``keys[i] format(v, formats[i])``, then ``print_ranking`` over the result's fitted
    tests; writes RESULTS / ``stem``.json (the rows, one per variant and test, keyed by ``keys``)."""
    import itertools  # noqa: PLC0415

    variants = list(itertools.product(*grid))
    record, params, settings = sensitivity_setup(result, "15x4s", variants, names, kn_factor=None)
    fitted, predicted = SPLITS[record["split"]]

    def label(values: tuple) -> str:
        return " ".join(f"{key} {format(v, spec)}" for key, v, spec in zip(keys, values, formats))

    files = data_copies()
    rows = []
    for name in sorted(files, key=lambda f: read_test(files[f]).p0):
        test = read_test(files[name])
        started = time.perf_counter()
        with np.errstate(all="ignore"):
            c = forward.simulate(test, params, settings)
        for i, v in enumerate(variants):
            m = metrics(test, c.q[i], c.eps_v[i])
            rows.append({"test": name, **dict(zip(keys, v)), **m, "fallbacks": int(c.n_fallback[i])})
            print(f"{name:15s} e0 {test.void_ratio:.3f} {label(v)}: RMS dq/qpk {m['rms_dq_over_qpeak']:.3f} RMS deps_v "
                  f"{100 * m['rms_deps_v']:.2f} % peak {100 * m['eps1_at_peak_model']:.2f} / "
                  f"{100 * m['eps1_at_peak_data']:.2f} %, fallbacks {int(c.n_fallback[i])}", flush=True)
        print(f"  ({len(variants)} variants in {time.perf_counter() - started:.0f} s)", flush=True)
    print(f"variants by the mean RMS abs(dq)/q_peak over the fitted tests {', '.join(fitted)} (predicted {predicted}):")
    print_ranking(rows, keys, fitted, label)
    (RESULTS / f"{stem}.json").write_text(json.dumps({"result": str(result), "grid": grid, "rows": rows}, indent=1))


def start_point(path: Path, params: tuple[str, ...] = PARAMS, kn_exponent: float | None = None) -> str:
    """--start-point of a study result's optimum (its log10 coordinates raised), or of this script's result's
    least-squares optimum (CLI names); ``kn_exponent`` where ``params`` holds it and the result does not."""
    optimum = json.loads(path.read_text())["optimum"]
    if "values" in optimum:  # this script's record
        values = dict(optimum["values"])
    else:
        values = {STUDY[k]: (10.0 ** v if k.startswith("log10_") else v) for k, v in optimum.items() if k in STUDY}
    if kn_exponent is not None:
        values.setdefault("kn_exponent", kn_exponent)
    return ",".join(f"{n}={values[n]!r}" for n in params)


def evaluate(out: Path, files: dict[str, Path], fitted: tuple[str, ...], predicted: str,
             check_rule: str = "") -> dict:
    """The three tests at the posterior mean and at the least-squares optimum of run.json's start; with
    ``check_rule`` (ORDERxSPINS[a|s]) also at the posterior mean on that orientation rule ("mean_on_RULE")."""
    post = post_mod.read_posterior(out)
    run = json.loads((out / "run.json").read_text())
    optimum = run.get("sampler", {}).get("start", {}).get("optimum") or run.get("start", {}).get("optimum")
    points = {"mean": (dict(post.mean), post.forward)}
    if optimum:
        points["optimum"] = ({**post.mean, **optimum}, post.forward)
    if check_rule:
        order, rest = check_rule.split("x")
        points[f"mean_on_{check_rule}"] = (dict(post.mean), replace(
            post.forward, lebedev_order=int(order), n_spins=int(rest[:-1]), staggered_spins=rest[-1] == "s"))
    result = {}
    for label, (values, settings) in points.items():
        rows, curves = {}, {}
        for name in sorted(files, key=lambda f: read_test(files[f]).p0):
            test = read_test(files[name])
            with np.errstate(all="ignore"):
                c = forward.simulate(test, {k: np.array([v]) for k, v in values.items()}, settings)
            rows[name] = {"role": "predicted" if name == predicted else "fitted", **metrics(test, c.q[0], c.eps_v[0]),
                          "forward_fallbacks": int(c.n_fallback[0])}
            curves[name] = {"eps1": test.eps1.tolist(), "q": c.q[0].tolist(), "eps_v": c.eps_v[0].tolist(),
                            "q_data": test.observed["q"].tolist(), "eps_v_data": test.observed["eps_v"].tolist()}
        print({"mean": "at the posterior mean:", "optimum": "at the start's least-squares optimum:"}.get(
            label, f"at the posterior mean, on the orientation rule {check_rule}:"))
        print_prediction_table(rows, fallbacks=True)
        result[label] = {"values": values, "tests": rows, "curves": curves}
    return result


def figure(result: dict, title: str, path: Path) -> None:
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (ax_q, ax_v) = plt.subplots(1, 2, figsize=(11, 4.2))
    for k, (name, c) in enumerate(result["mean"]["curves"].items()):
        role = result["mean"]["tests"][name]["role"]
        e = 100 * np.asarray(c["eps1"])
        label = f"{name.split('_')[1].replace('kpa.csv', ' kPa')} ({role})"
        style = "--" if role == "predicted" else "-"
        ax_q.plot(e, np.asarray(c["q_data"]) / 1e3, ".", color=f"C{k}", ms=3)
        ax_q.plot(e, np.asarray(c["q"]) / 1e3, style, color=f"C{k}", label=label)
        ax_v.plot(e, 100 * np.asarray(c["eps_v_data"]), ".", color=f"C{k}", ms=3)
        ax_v.plot(e, 100 * np.asarray(c["eps_v"]), style, color=f"C{k}")
    ax_q.set(xlabel="eps1 [%]", ylabel="q [kPa]")
    ax_v.set(xlabel="eps1 [%]", ylabel="eps_v [%] (contraction > 0)")
    ax_q.legend(fontsize=8)
    fig.suptitle(title + " (dots: data; lines: model at the posterior mean)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rule_of(command: str) -> str:
    """"Lebedev 15 x 4 staggered" of a calibrate command line (its --order, --spins, --staggered-spins)."""
    words = shlex.split(command)
    order = words[words.index("--order") + 1] if "--order" in words else "11"
    spins = words[words.index("--spins") + 1] if "--spins" in words else "4"
    return f"Lebedev {order} x {spins} {'staggered' if '--staggered-spins' in words else 'aligned'}"


def splits_figure(rows: list[str], out: Path) -> None:
    """One row per argument (q and eps_v against eps1, data and posterior means' curves), for the docs; an argument
    "A.json+B.json" draws A's model thin and B's thick (one split, two calibrations)."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 3.6 * len(rows)), squeeze=False)
    for (ax_q, ax_v), row in zip(axes, rows):
        paths = [Path(p) for p in row.split("+")]
        for j, path in enumerate(paths):
            result = json.loads(path.read_text())
            thick = j == len(paths) - 1
            for k, (name, c) in enumerate(result["mean"]["curves"].items()):
                role = result["mean"]["tests"][name]["role"]
                e = 100 * np.asarray(c["eps1"])
                style = ("--" if role == "predicted" else "-") if thick else ":"
                if thick:
                    ax_q.plot(e, np.asarray(c["q_data"]) / 1e3, ".", color=f"C{k}", ms=2)
                    ax_v.plot(e, 100 * np.asarray(c["eps_v_data"]), ".", color=f"C{k}", ms=2)
                label = f"{name.split('_')[1].replace('kpa.csv', ' kPa')} ({role}), {rule_of(result['command'])}"
                ax_q.plot(e, np.asarray(c["q"]) / 1e3, style, color=f"C{k}", lw=1.6 if thick else 0.9,
                          label=label if thick or k == 0 else None)
                ax_v.plot(e, 100 * np.asarray(c["eps_v"]), style, color=f"C{k}", lw=1.6 if thick else 0.9)
        ax_q.set(xlabel="eps1 [%]", ylabel="q [kPa]", title=f"split {result['split']}")
        ax_v.set(xlabel="eps1 [%]", ylabel="eps_v [%] (contraction > 0)")
        ax_q.legend(fontsize=7)
    fig.suptitle("Dobrany sand, hmodel calibrate --interlocking: dots data, lines the posterior means "
                 "(dotted: the other rule)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--splits-figure":  # OUT.png RESULT.json ...
        splits_figure(sys.argv[3:], Path(sys.argv[2]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=tuple(SPLITS), required=True)
    parser.add_argument("--tag", required=True)
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--kn-exponent", default="0.3333333333333333")
    parser.add_argument("--start-from", type=Path, help="a study result JSON whose optimum starts the fit")
    parser.add_argument("--extra", default="", help="more hmodel calibrate flags")
    parser.add_argument("--evaluate-only", action="store_true", help="evaluate an existing calibration folder")
    parser.add_argument("--check-rule", default="", help="ORDERxSPINS[a|s]: also the mean's curves on that rule")
    parser.add_argument("--fit-kn-exponent", action="store_true", help="calibrate kn's exponent (prior [0, 1])")
    parser.add_argument("--fit-mobilisation", default="", metavar="A,R0",
                        help="calibrate mobilisation_strain and mobilisation_start too, started at A and R0")
    parser.add_argument("--fit-decay", default="", metavar="G,K",
                        help="calibrate relax_strain and relax_exponent too, started at G and K")
    parser.add_argument("--fit-softening", default="", metavar="G,K",
                        help="calibrate softening_strain and relax_exponent too, started at G and K")
    parser.add_argument("--fit-void-lag", default="", metavar="G,K,S|G,S",
                        help="calibrate relax_strain, relax_exponent and relax_void_slope too, started at G, K, S "
                             "(G,S: relax_exponent 0, not calibrated)")
    parser.add_argument("--fit-mobilisation-void", default="", metavar="A,R0,S",
                        help="calibrate mobilisation_strain, mobilisation_start and mobilisation_void_slope too, "
                             "started at A, R0 and S")
    parser.add_argument("--fit-state-map", default="", metavar="W",
                        help="calibrate map_state_weight too (prior [0, 2]), started at W")
    parser.add_argument("--state-map-prior", default="", metavar="LOW,HIGH",
                        help="with --fit-state-map: its prior's bounds instead of 0,2 (within [-2, 2])")
    parser.add_argument("--fit-stiffness-void", default="", metavar="S",
                        help="calibrate stiffness_void_slope too (prior [0, 30]), started at S")
    parser.add_argument("--kn-factor", type=float, default=1.0,
                        help="with --fit-mobilisation, --fit-decay, --fit-softening, --fit-void-lag or "
                             "--fit-mobilisation-void, --fit-state-map or --fit-stiffness-void: kn's start factor")
    args = parser.parse_args(argv)
    if args.fit_mobilisation and args.fit_mobilisation_void:
        parser.error("--fit-mobilisation and --fit-mobilisation-void: one of them")
    params = PARAMS + (("kn_exponent",) if args.fit_kn_exponent else ())
    params += MOBILISATION if args.fit_mobilisation else ()
    params += MOBILISATION_VOID if args.fit_mobilisation_void else ()
    params += tuple(STATE_MAP_PRIOR) if args.fit_state_map else ()
    params += tuple(STIFFNESS_VOID_PRIOR) if args.fit_stiffness_void else ()
    state_map_prior = ({"map_state_weight": [float(v) for v in args.state_map_prior.split(",")]}
                       if args.state_map_prior else STATE_MAP_PRIOR)
    if sum(map(bool, (args.fit_decay, args.fit_softening, args.fit_void_lag))) > 1:
        parser.error("--fit-decay, --fit-softening and --fit-void-lag: one lag at a time")
    params += DECAY if args.fit_decay else ()
    params += SOFTENING if args.fit_softening else ()
    void_lag = VOID_LAG if len(args.fit_void_lag.split(",")) == 3 else ("relax_strain", "relax_void_slope")
    params += void_lag if args.fit_void_lag else ()
    exponent = ["--kn-exponent", args.kn_exponent] if not args.fit_kn_exponent else []
    files = data_copies()
    fitted, predicted = SPLITS[args.split]
    out = RUNS / f"{args.split.replace('+', '_')}_{args.tag}"
    prior = RUNS / ("prior" + "_kn_exponent" * args.fit_kn_exponent + "_mobilisation" * bool(args.fit_mobilisation)
                    + "_decay" * bool(args.fit_decay) + "_softening" * bool(args.fit_softening)
                    + "_void_lag" * bool(args.fit_void_lag)
                    + "_k0" * (len(void_lag) == 2 and bool(args.fit_void_lag))
                    + "_mobilisation_void" * bool(args.fit_mobilisation_void)
                    + "_state_map" * bool(args.fit_state_map)
                    + ("_" + args.state_map_prior.replace(",", "_")) * bool(args.state_map_prior)
                    + "_stiffness_void" * bool(args.fit_stiffness_void) + ".json")
    prior.write_text(json.dumps({**PRIOR, **({"kn_exponent": [0.0, 1.0]} if args.fit_kn_exponent else {}),
                                 **(MOBILISATION_PRIOR if args.fit_mobilisation else {}),
                                 **(DECAY_PRIOR if args.fit_decay else {}),
                                 **(SOFTENING_PRIOR if args.fit_softening else {}),
                                 **({n: VOID_LAG_PRIOR[n] for n in void_lag} if args.fit_void_lag else {}),
                                 **(MOBILISATION_VOID_PRIOR if args.fit_mobilisation_void else {}),
                                 **(state_map_prior if args.fit_state_map else {}),
                                 **(STIFFNESS_VOID_PRIOR if args.fit_stiffness_void else {})},
                                indent=1))
    command = [sys.executable, "-m", "homogenization.calibrate", *sum((["--data", str(files[f])] for f in fitted), []),
               "--params", ",".join(params), "--prior", str(prior), *exponent, *FLAGS,
               "--steps", str(args.steps), "--out", str(out), *shlex.split(args.extra)]
    if args.start_from is not None:
        start = start_point(args.start_from, PARAMS + (("kn_exponent",) if args.fit_kn_exponent else ()),
                            float(args.kn_exponent))
        if (args.fit_mobilisation or args.fit_decay or args.fit_softening or args.fit_void_lag
                or args.fit_mobilisation_void or args.fit_state_map or args.fit_stiffness_void):
            values = dict(item.split("=") for item in start.split(","))
            values["kn"] = repr(float(values["kn"]) * args.kn_factor)
            for names, text in ((MOBILISATION, args.fit_mobilisation), (DECAY, args.fit_decay),
                                (SOFTENING, args.fit_softening), (void_lag, args.fit_void_lag),
                                (MOBILISATION_VOID, args.fit_mobilisation_void),
                                (tuple(STATE_MAP_PRIOR), args.fit_state_map),
                                (tuple(STIFFNESS_VOID_PRIOR), args.fit_stiffness_void)):
                if text:
                    values.update(zip(names, (repr(float(v)) for v in text.split(","))))
            start = ",".join(f"{k}={v}" for k, v in values.items())
        command += ["--start-point", start]
    print("command:", shlex.join(command), flush=True)
    print(f"nice {os.nice(0)}, load {os.getloadavg()[0]:.1f}", flush=True)
    seconds = None
    if not args.evaluate_only:
        started = time.perf_counter()
        subprocess.run(command, check=True)
        seconds = time.perf_counter() - started
        print(f"hmodel calibrate wall time: {seconds:.0f} s, load {os.getloadavg()[0]:.1f}", flush=True)
    run = json.loads((out / "run.json").read_text())
    result = evaluate(out, files, fitted, predicted, args.check_rule)
    sampler = run.get("sampler", {})
    auto = sampler.get("autocorrelation", {})
    print("sampler: " + json.dumps({k: auto.get(k) for k in ("tau_steps", "steps_per_tau", "converged",
                                                            "steps_needed", "steps_retained")}))
    print("acceptance: " + json.dumps(sampler.get("acceptance_fraction", sampler.get("acceptance"))))
    record = {"split": args.split, "tag": args.tag, "command": shlex.join(command), "wall_seconds": seconds,
              "sampler": sampler, "start": run.get("start", sampler.get("start")), **result}
    stem = f"calibration_dobrany_product_{args.split.replace('+', '_')}_{args.tag}"
    if seconds is None and (RESULTS / f"{stem}.json").is_file():  # --evaluate-only keeps the run's record
        before = json.loads((RESULTS / f"{stem}.json").read_text())
        record.update(wall_seconds=before.get("wall_seconds"), command=before.get("command", record["command"]))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(record, indent=1, default=str))
    figure(result, f"Dobrany sand, hmodel calibrate --interlocking, split {args.split}, {args.tag}",
           RESULTS / f"{stem}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
