"""python studies/bench_real_sand.py [--split 50+200|50+100] [--start map|prior] [--walkers 16] [--steps 100]
[--channels q,eps_v|q] [--params phi_g,kn,kt_over_kn,alpha0[,alpha0_spread]] [--increment 2e-3] [--band 20]
[--out runs/real_sand_SPLIT]

The H-model on a real sand: ``hmodel calibrate`` on two of the drained triaxial tests of Dobrany
sand (benchmarks/lab_data/dobrany_sand/, measured; --split 50+200: the 50 and 200 kPa tests,
50+100: the 50 and 100 kPa tests), then ``hmodel triaxial --posterior`` at each of 50, 100 and
200 kPa, the third test being one the calibration never saw. Prints, per test, the misfit of the run at the posterior mean against the measured curve:

- RMS |dq| / q_peak: root-mean-square of q_model - q_data at the data's eps1, over the measured
  peak of q [-];
- RMS d eps_v: root-mean-square of eps_v,model - eps_v,data [-] (eps_v = eps11 + eps22 + eps33
  since the end of the isotropic stage, contraction positive: the data's convention);
- peak q and the axial strain at peak, model against data; eps_v at the last measured eps1
  (negative: dilated);

and the sampler's diagnostics of run.json (autocorrelation times, effective samples, whether the
chain is shorter than 50 tau). The predictions run on the calibration's own rule (Lebedev order
11 x 4 aligned spins) and increment, so that they are the model the posterior was fitted with,
and draw a 95 % band of --band posterior sets (posterior_band.csv in each prediction folder).

The calibration resumes (and a larger --steps extends it) in --out/calibration; everything is
written under --out; the summary goes to stdout and --out/summary.json, the figure (q and eps_v
of the data, the run at the posterior mean and its 95 % band, each test) to --out/real_sand.png.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from homogenization.calibration.data import read_test

DATA = Path(__file__).resolve().parents[1] / "benchmarks" / "lab_data" / "dobrany_sand"
SPLITS = {"50+200": (("cid_50kpa.csv", "cid_200kpa.csv"), "cid_100kpa.csv"),
          "50+100": (("cid_50kpa.csv", "cid_100kpa.csv"), "cid_200kpa.csv")}
"""--split: (the fitted tests, the predicted one)."""
PRIOR = {"kn": [3e6, 3e8]}
"""Prior narrowed from the 3D default (kn 1e6-1e10 N/m): at kn above a few 1e8 N/m the closed form's
drained test at these pressures gives up (Newton fallbacks at every increment, NaN curves) after
30 Newton iterations per increment, which makes a population of prior draws take minutes; between
3e6 and 3e8 N/m the closed form's peak q / p0 spans 2 to 7 at 1e5 Pa (the data: 3.5 to 5.8; a
grid search found the linear law's best near 8e7 N/m, docs/calibration.md)."""


def restricted(path: Path, channels: list[str], folder: Path) -> Path:
    """``path`` itself when it holds exactly ``channels``, else a copy with only eps1 and ``channels`` in ``folder``."""
    lines = path.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    names = lines[header].split(",")
    if names[1:] == channels:
        return path
    keep = [0] + [names.index(c) for c in channels]
    rows = [",".join(line.split(",")[k] for k in keep) for line in lines[header:]]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / path.name).write_text("\n".join([*lines[:header], *rows]) + "\n")
    return folder / path.name


def hmodel(*argv: str) -> None:
    """Run an hmodel command in a subprocess (its output passed through); exit on failure."""
    command = [sys.executable, "-m", "homogenization.cli.hmodel", *argv]
    print("$ hmodel " + " ".join(argv), flush=True)
    if subprocess.run(command).returncode != 0:
        raise SystemExit(f"failed: hmodel {' '.join(argv)}")


def model_curve(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """eps1, q [Pa] and eps_v [-] of the shear stage of curve.csv, counted from the end of the isotropic stage."""
    rows = [line.split(",") for line in (folder / "curve.csv").read_text().splitlines()[1:]]
    iso = np.array([float(v) for v in [r for r in rows if r[0] == "iso"][-1][1:]])
    shear = np.array([[float(v) for v in r[1:]] for r in rows if r[0] == "shear"])
    e11, e22, e33, q = shear[:, 0], shear[:, 1], shear[:, 2], shear[:, 7]
    return e11 - iso[0], q, (e11 + e22 + e33) - (iso[0] + iso[1] + iso[2])


def compare(data_file: Path, folder: Path) -> dict[str, float]:
    """Misfit of the run in ``folder`` against the measured ``data_file`` (module docstring)."""
    test = read_test(data_file)
    e1, q, ev = model_curve(folder)
    qm, evm = np.interp(test.eps1, e1, q), np.interp(test.eps1, e1, ev)
    qd, evd = test.observed["q"], test.observed["eps_v"]
    i_m, i_d = int(np.argmax(q)), int(np.argmax(qd))
    return {
        "p0": test.p0,
        "rms_dq_over_qpeak": float(np.sqrt(np.mean((qm - qd) ** 2)) / qd.max()),
        "rms_deps_v": float(np.sqrt(np.mean((evm - evd) ** 2))),
        "q_peak_model": float(q[i_m]), "q_peak_data": float(qd[i_d]),
        "eps1_at_peak_model": float(e1[i_m]), "eps1_at_peak_data": float(test.eps1[i_d]),
        "eps_v_end_model": float(evm[-1]), "eps_v_end_data": float(evd[-1]), "eps1_end": float(test.eps1[-1]),
    }


def forward_at_mean(posterior: Path, data_file: Path) -> dict[str, float]:
    """``compare``'s misfits of the calibration's own forward model (``forward.simulate``, the last
    Newton iterate kept where the drained control does not converge: counted) at the posterior mean,
    at the data's eps1; for a test whose ``hmodel triaxial`` run stops on an unconverged increment."""
    from homogenization.calibration.forward import simulate  # noqa: PLC0415
    from homogenization.calibration.posterior import read_posterior  # noqa: PLC0415

    post, test = read_posterior(posterior), read_test(data_file)
    with np.errstate(all="ignore"):
        c = simulate(test, {k: np.array([v]) for k, v in post.mean.items()}, post.forward)
    q, ev = c.q[0], c.eps_v[0]
    qd, evd = test.observed["q"], test.observed["eps_v"]
    i_m, i_d = int(np.argmax(q)), int(np.argmax(qd))
    return {
        "p0": test.p0, "model": "forward model at the posterior mean", "forward_fallbacks": int(c.n_fallback[0]),
        "rms_dq_over_qpeak": float(np.sqrt(np.mean((q - qd) ** 2)) / qd.max()),
        "rms_deps_v": float(np.sqrt(np.mean((ev - evd) ** 2))),
        "q_peak_model": float(q[i_m]), "q_peak_data": float(qd[i_d]),
        "eps1_at_peak_model": float(test.eps1[i_m]), "eps1_at_peak_data": float(test.eps1[i_d]),
        "eps_v_end_model": float(ev[-1]), "eps_v_end_data": float(evd[-1]), "eps1_end": float(test.eps1[-1]),
    }


def band(folder: Path) -> dict[str, np.ndarray]:
    """Columns of the prediction's posterior_band.csv (``homogenization.calibration.posterior.band_columns``)."""
    lines = [line for line in (folder / "posterior_band.csv").read_text().splitlines() if not line.startswith("#")]
    table = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    return dict(zip(lines[0].split(","), table.T))


def figure(folders: dict[str, Path], roles: dict[str, str], title: str, path: Path) -> None:
    """q and eps_v against eps1 of every test: the data, the run at the posterior mean and the 95 % band."""
    from matplotlib.figure import Figure  # noqa: PLC0415

    from homogenization.output.figure_style import apply_style, figure_legend  # noqa: PLC0415
    from homogenization.output.figures import save_figure  # noqa: PLC0415

    fig = Figure(figsize=(10, 4.4), layout="constrained")
    ax_q, ax_v = fig.subplots(1, 2)
    handles = []
    for k, (name, folder) in enumerate(folders.items()):
        test, b, colour = read_test(DATA / name), band(folder), f"C{k}"
        e1, q, ev = model_curve(folder)
        label = f"{test.p0 / 1e3:g} kPa ({roles[name]})"
        for ax, data, model, key, scale in ((ax_q, test.observed["q"], q, "q", 1e-3),
                                            (ax_v, test.observed["eps_v"], ev, "eps_v", 100.0)):
            h_band = ax.fill_between(100 * b["eps1"], scale * b[f"{key}_lo"], scale * b[f"{key}_hi"], color=colour,
                                     alpha=0.25, label=f"{label}: 95 % posterior band")
            (h_model,) = ax.plot(100 * e1, scale * model, color=colour, ls="--" if roles[name] == "predicted" else "-",
                                 label=f"{label}: model at the posterior mean")
            (h_data,) = ax.plot(100 * test.eps1, scale * data, "o", ms=2, color=colour, label=f"{label}: measured")
            if ax is ax_q:
                handles += [h_data, h_model, h_band]
    ax_q.set(xlabel="axial strain eps1 [%]", ylabel="q [kPa]")
    ax_v.set(xlabel="axial strain eps1 [%]", ylabel="eps_v [%] (contraction +)")
    fig.suptitle(title)
    figure_legend(fig, handles, max_columns=3)
    save_figure(apply_style(fig), path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1])
    parser.add_argument("--split", choices=tuple(SPLITS), default="50+200", help="the fitted tests (kPa)")
    parser.add_argument("--start", choices=("map", "prior"), default="map", help="hmodel calibrate --start")
    parser.add_argument("--channels", default="q,eps_v",
                        help="measured channels the calibration fits (q,eps_v or q): the fitted tests' files "
                             "restricted to them are written to --out/data")
    parser.add_argument("--params", default="phi_g,kn,kt_over_kn,alpha0",
                        help="hmodel calibrate --params (add alpha0_spread for a spread of opening angles)")
    parser.add_argument("--walkers", type=int, default=16)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--increment", type=float, default=2e-3, help="forward and prediction increment [-]")
    parser.add_argument("--band", type=int, default=20, help="posterior draws of each prediction's band")
    parser.add_argument("--out", type=Path, default=None, help="default runs/real_sand_SPLIT")
    args = parser.parse_args(argv)
    fitted, predicted = SPLITS[args.split]
    args.out = args.out or Path(f"runs/real_sand_{args.split.replace('+', '_')}")
    cal = args.out / "calibration"
    args.out.mkdir(parents=True, exist_ok=True)
    prior = args.out / "prior.json"
    prior.write_text(json.dumps(PRIOR) + "\n")
    start = time.perf_counter()
    channels = args.channels.split(",")
    hmodel("calibrate", *[a for f in fitted for a in ("--data", str(restricted(DATA / f, channels, args.out / "data")))],
           "--params", args.params, "--prior", str(prior), "--start", args.start,
           "--walkers", str(args.walkers), "--steps", str(args.steps),
           "--increment", f"{args.increment:g}", "--iso-increment", f"{args.increment / 2:g}", "--confirm", "none",
           "--out", str(cal))
    seconds_calibration = time.perf_counter() - start
    results = {}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = read_test(DATA / name)
        folder = args.out / f"predict_{name.removesuffix('.csv')}"
        role = "predicted" if name == predicted else "fitted"
        try:
            hmodel("triaxial", "--posterior", str(cal / "posterior.json"), "--posterior-band", str(args.band),
                   "--drained", "--p0", f"{test.p0:g}", "--eps-max", f"{test.eps1[-1]:.4g}",
                   "--increment", f"{args.increment:g}", "--iso-increment", f"{args.increment / 2:g}",
                   "--order", "11", "--spins", "4", "--aligned-spins", "-q", "--overwrite", "--out", str(folder))
        except SystemExit as exc:
            print(f"{exc}; its misfit below is the calibration's forward model at the posterior mean", flush=True)
            results[name] = {"role": role, **forward_at_mean(cal / "posterior.json", DATA / name)}
            continue
        results[name] = {"role": role, "model": "hmodel triaxial at the posterior mean", **compare(DATA / name, folder)}
    ran = [name for name, r in results.items() if r["model"].startswith("hmodel")]
    figure({name: args.out / f"predict_{name.removesuffix('.csv')}" for name in ran},
           {name: r["role"] for name, r in results.items()},
           f"Dobrany sand, drained triaxial: fitted {' + '.join(f.split('_')[1].removesuffix('kpa.csv') for f in fitted)} "
           f"kPa ({args.channels}), predicted {predicted.split('_')[1].removesuffix('kpa.csv')} kPa",
           args.out / "real_sand.png")
    run = json.loads((cal / "run.json").read_text())
    summary = {"split": args.split, "start": run.get("start"), "posterior": run["posterior"], "sampler": run["sampler"],
               "forward_model": {k: v for k, v in run["forward_model"].items() if k != "settings"},
               "seconds_calibration": seconds_calibration, "tests": results,
               "load_average_at_end": list(os.getloadavg()),
               "settings": {"split": args.split, "channels": args.channels, "start": args.start, "walkers": args.walkers,
                            "steps": args.steps, "increment": args.increment, "params": args.params,
                            "band": args.band}}
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"calibration: {args.walkers} walkers x {run['sampler']['steps']} steps, {seconds_calibration:.0f} s wall")
    for name, s in run["posterior"].items():
        print(f"  {name}: mean {s['mean']:.4g} {s['unit']}, 95 % [{s['ci95'][0]:.4g}, {s['ci95'][1]:.4g}]")
    auto = run["sampler"]["autocorrelation"]
    print(f"  tau [steps]: {auto['tau_steps']}; effective samples: {auto['effective_samples']} of {auto['samples']}; "
          f"{auto['steps_per_tau']} retained steps per largest tau (short: {auto['short']})")
    print_prediction_table(results)
    return 0


def print_prediction_table(results: dict, fallbacks: bool = False) -> None:
    """Print one row per test: RMS |dq|/q_peak, RMS d eps_v, peak q, strain at peak and final eps_v,
    model against data (and the forward model's fallbacks where ``fallbacks``)."""
    print("test            role       RMS|dq|/q_pk  RMS d eps_v  q_pk model/data [kPa]  eps1 at pk model/data [%]  "
          "eps_v end model/data [%]" + ("  fallbacks" if fallbacks else ""))
    for name, r in results.items():
        print(f"{name:15s} {r['role']:10s} {r['rms_dq_over_qpeak']:12.3f}  {r['rms_deps_v']:11.4f}  "
              f"{r['q_peak_model'] / 1e3:8.0f} / {r['q_peak_data'] / 1e3:<8.0f}     "
              f"{100 * r['eps1_at_peak_model']:6.1f} / {100 * r['eps1_at_peak_data']:<6.1f}             "
              f"{100 * r['eps_v_end_model']:6.2f} / {100 * r['eps_v_end_data']:<6.2f}"
              + (f"   {r['forward_fallbacks']}" if fallbacks else ""))


if __name__ == "__main__":
    raise SystemExit(main())
