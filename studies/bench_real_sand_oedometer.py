"""python studies/bench_real_sand_oedometer.py [--posterior studies/results/real_sand_50_200.json]
[--calibration DIR] [--increment 1e-3] [--hertz G] [--out runs/real_sand_oedometer]

The 3D H-model on an oedometer test it was not fitted to: the loading-unloading curve of the loose
Dobrany sand specimen (benchmarks/lab_data/dobrany_sand/oed_loose.csv, sheet OED-REC-1, e0 0.996,
vertical stress 8 kPa - 1.2 MPa - 10 kPa) against ``hmodel triaxial --oedometer`` (closed form,
the calibration's rule of Lebedev order 11 x 4 aligned spins) at the posterior mean of the
calibration on the drained triaxial tests (the ``posterior`` means of --posterior, the summary
json of ``bench_real_sand.py``), with the linear contact law it was fitted with; ``--hertz G`` runs
the Hertz-Mindlin law of grains of shear modulus G [Pa] (Poisson ratio 0.2) instead, at the
posterior's phi_g and alpha0 (not fitted: the calibration reads the linear law only). ``--calibration DIR``
runs ``hmodel triaxial --posterior DIR`` instead (an ``hmodel calibrate`` folder: its law at the posterior
mean, with its alpha0_spread or its critical-state rule where it has one). ``--optimum FILE.json`` (a result of
``bench_real_sand_critical_state.py``) writes its least-squares optimum as a one-point posterior folder
(posterior.json with the rule, run.json with that study's forward settings) under --out and runs it the same way.
``--void-ratio E`` runs the specimen at void ratio E on a calibration's map (``loosest``: its e_max, where the
specimen's 0.996 lies beyond the fitted map).

The model is seated isotropically at the data's first stress (8 kPa), then loaded with the
lateral strains held at zero. A first run loads far enough to find the axial strain at which
sigma_v reaches the data's largest stress (1.2 MPa, linear interpolation, rounded up to
--increment); the second loads to that strain and unloads by the same strain, and its unloading
branch is read down to the data's last stress (10 kPa). Prints, model against data:

- the constrained modulus M = d sigma_v / d eps_a (secant over consecutive measured stress
  levels of the loading branch) at low (40 - 80 kPa) and high (600 kPa - 1.2 MPa) stress;
- the unloading modulus over the first unloading interval (1.2 MPa - 600 kPa) and its ratio to the
  loading modulus over the same stresses;
- the axial strain at 1.2 MPa and the strain left after unloading to 10 kPa (irrecoverable part);
- the RMS difference of the axial strain at the measured stress levels, loading branch and unloading branch;
- K0 = sigma_h / sigma_v of the model at 80 kPa and 1.2 MPa and after unloading (the oedometer
  measures no lateral stress; beside it, Jaky's 1 - sin(phi) with the sand's angle of repose,
  35.5 deg, an empirical estimate, not a measurement).

Everything goes under --out (the two runs, summary.json, oedometer.png: sigma_v against eps_a of
data and model, and K0 against sigma_v).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "benchmarks" / "lab_data" / "dobrany_sand" / "oed_loose.csv"
POSTERIOR = ROOT / "studies" / "results" / "real_sand_50_200.json"
RULE = ("--order", "11", "--spins", "4", "--aligned-spins")
"""The calibration's rule (docs/calibration.md, A real sand)."""
REPOSE_DEG = 35.5
"""Angle of repose of Dobrany sand [deg] (benchmarks/lab_data/dobrany_sand/README.md)."""
LOW, HIGH = (40e3, 80e3), (600e3, 1200e3)
"""Stress intervals [Pa] of the constrained moduli (consecutive measured loading levels)."""


def read_data(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(sigma_a [Pa], eps_a [-]) of the loading branch (up to the largest stress) and of the unloading
    branch (from it on), in the order of the test."""
    rows = [line for line in path.read_text().splitlines() if line and not line.startswith("#")]
    table = list(csv.DictReader(rows))
    sigma = np.array([float(r["sigma_a"]) for r in table])
    eps = np.array([float(r["eps_a"]) for r in table])
    top = int(np.argmax(sigma))
    return sigma[:top + 1], eps[:top + 1], sigma[top:], eps[top:]


def read_model(folder: Path) -> dict[str, np.ndarray]:
    """Columns of the run's oedometer.csv (stage as str, the rest float)."""
    with open(folder / "oedometer.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    return {key: np.array([r[key] for r in rows]) if key == "stage" else np.array([float(r[key]) for r in rows])
            for key in rows[0]}


def strain_at(sigma: np.ndarray, eps: np.ndarray, level: float) -> float:
    """Axial strain where a monotonic branch (sigma, eps) passes the stress ``level`` (linear interpolation)."""
    order = np.argsort(sigma)
    if not sigma.min() <= level <= sigma.max():
        return math.nan
    return float(np.interp(level, sigma[order], eps[order]))


def modulus(sigma: np.ndarray, eps: np.ndarray, interval: tuple[float, float]) -> float:
    """Secant modulus [Pa] of a branch between two stress levels: d sigma / |d eps|."""
    lo, hi = interval
    return (hi - lo) / abs(strain_at(sigma, eps, hi) - strain_at(sigma, eps, lo))


def rms_strain(model: tuple[np.ndarray, np.ndarray], sigma: np.ndarray, eps: np.ndarray) -> float:
    """RMS [-] of the model's axial strain minus the data's at the data's stress levels of a branch (a level the
    model's branch does not reach counts as NaN)."""
    return float(np.sqrt(np.mean([(strain_at(*model, level) - e) ** 2 for level, e in zip(sigma, eps)])))


def point_posterior(result: dict, folder: Path, rule: bool = True) -> Path:
    """An hmodel calibrate folder holding only what ``hmodel triaxial --posterior`` reads (posterior.json,
    run.json) for the least-squares optimum of a ``bench_real_sand_critical_state.py`` result: every fitted
    coordinate as a calibrated parameter at its value, the rule (``DEFAULTS[3]`` with alpha_c and the rate
    fitted; none where not ``rule``) and that study's forward settings."""
    from dataclasses import asdict, replace  # noqa: PLC0415

    from homogenization.material.critical_state import DEFAULTS  # noqa: PLC0415
    from warp_hcell.core.parameters import CellDefaults  # noqa: PLC0415

    x = result["optimum"]
    values = {"phi_g": x["phi_g"], "kn": 10.0 ** x["log10_kn"], "kt_over_kn": x["kt_over_kn"]}
    values.update({k: x[k] for k in ("alpha0", "e_min", "e_max") if k in x})
    fitted = replace(DEFAULTS[3], **({"alpha_c_deg": x["alpha_c_deg"]} if "alpha_c_deg" in x else {}),
                   **({"rate": 10.0 ** x["log10_rate"]} if "log10_rate" in x else {}))
    folder.mkdir(parents=True, exist_ok=True)
    posterior = {k: {"mean": v, "median": v, "ci95": [v, v]} for k, v in values.items()}
    (folder / "posterior.json").write_text(json.dumps({**posterior, **({"critical_state": asdict(fitted)} if rule else {})},
                                                      indent=1))
    fixed = {"phi_g": values["phi_g"], "kn": values["kn"], "kt_over_kn": values["kt_over_kn"],
             "alpha0": values.get("alpha0", 55.0)}
    forward = {**result["settings"], "radius": CellDefaults.radius, "fixed": fixed, "staggered_spins": False}
    (folder / "run.json").write_text(json.dumps({"data_dimensions": [3], "config": {"forward": forward}}, indent=1))
    return folder


def hmodel(*args: str) -> None:
    command = [sys.executable, "-m", "homogenization.hmodel", *args]
    print("$ hmodel " + " ".join(args), flush=True)
    if subprocess.run(command, check=False).returncode != 0:
        raise SystemExit(f"bench_real_sand_oedometer: hmodel {args[0]} failed (its error above)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[1])
    parser.add_argument("--posterior", type=Path, default=POSTERIOR,
                        help="summary json whose 'posterior' holds the means of phi_g, kn, kt_over_kn, alpha0")
    parser.add_argument("--increment", type=float, default=1e-3, help="axial strain increment [-]")
    parser.add_argument("--hertz", type=float, default=None, metavar="G",
                        help="Hertz-Mindlin law of grain shear modulus G [Pa] instead of the posterior's kn, kt")
    parser.add_argument("--calibration", type=Path, default=None,
                        help="an hmodel calibrate folder: hmodel triaxial --posterior DIR instead of --posterior's means")
    parser.add_argument("--optimum", type=Path, default=None,
                        help="a bench_real_sand_critical_state.py result json: its optimum as a one-point posterior")
    parser.add_argument("--plain", action="store_true", help="--optimum without its critical-state rule")
    parser.add_argument("--void-ratio", default=None, help="void ratio E of the specimen on the calibration's map, or "
                                                           "'loosest' (its e_max)")
    parser.add_argument("--out", type=Path, default=Path("runs/real_sand_oedometer"))
    args = parser.parse_args(argv)
    if args.optimum is not None:
        args.calibration = point_posterior(json.loads(args.optimum.read_text()), args.out / "point_posterior",
                                           rule=not args.plain)
    if args.calibration is not None and args.hertz is not None:
        parser.error("--calibration runs the calibration's own law: drop --hertz")
    if args.calibration is not None:
        post = {name: {"mean": entry["mean"]} for name, entry in
                json.loads((args.calibration / "posterior.json").read_text()).items()
                if isinstance(entry, dict) and "mean" in entry}
        fixed = json.loads((args.calibration / "run.json").read_text())["config"]["forward"]["fixed"]
        post = {**{name: {"mean": value} for name, value in fixed.items()}, **post}
    else:
        post = json.loads(args.posterior.read_text())["posterior"]
    mean = {name: post[name]["mean"] for name in ("phi_g", "kn", "kt_over_kn", "alpha0", "alpha0_spread", "e_min", "e_max",
                                                  "alpha_c", "renewal_rate") if name in post}
    state = ()
    if args.void_ratio is not None:
        e0 = mean["e_max"] if args.void_ratio == "loosest" else float(args.void_ratio)
        mean["void_ratio"] = e0
        state = ("--void-ratio", repr(e0))
    source = args.calibration / "posterior.json" if args.calibration is not None else args.posterior
    load_s, load_e, unload_s, unload_e = read_data(DATA)
    seat, top, bottom = float(load_s[0]), float(load_s[-1]), float(unload_s[-1])
    law = (("--kn", f"{mean['kn']:.4g}", "--kt", f"{mean['kt_over_kn'] * mean['kn']:.4g}") if args.hertz is None else
           ("--law", "hertz-mindlin", "--shear-modulus", f"{args.hertz:g}", "--poisson", "0.2"))
    cell = ("--p0", f"{seat:g}", "--alpha0", f"{mean['alpha0']:.4g}", *law, "--phi", f"{mean['phi_g']:.4g}", *RULE,
            "--increment", f"{args.increment:g}", "-q", "--overwrite")
    if args.calibration is not None:
        cell = ("--p0", f"{seat:g}", "--posterior", str(args.calibration), *state, *RULE, "--increment",
                f"{args.increment:g}", "-q", "--overwrite")
    args.out.mkdir(parents=True, exist_ok=True)
    probe = args.out / "probe"
    hmodel("triaxial", "--oedometer", "0", "--eps-max", "0.3", *cell, "--out", str(probe))
    first = read_model(probe)
    loading = first["stage"] == "load"
    eps_top = strain_at(first["sigma_v"][loading], first["eps_a"][loading], top) - first["eps_a"][~loading][-1]
    if not math.isfinite(eps_top):
        raise SystemExit(f"the model does not reach {top:g} Pa by an axial strain of 0.3")
    eps_load = math.ceil(eps_top / args.increment) * args.increment
    run = args.out / "model"
    hmodel("triaxial", "--oedometer", f"{eps_load:.6g}", "--eps-max", f"{eps_load:.6g}", *cell, "--out", str(run))
    model = read_model(run)
    seated = model["eps_a"][model["stage"] == "iso"][-1]
    eps_a = model["eps_a"] - seated  # axial strain since seating, as the data's
    up, down = model["stage"] == "load", model["stage"] == "unload"
    down_idx = np.flatnonzero(down)
    above = down_idx[model["sigma_v"][down_idx] >= bottom]
    down_idx = down_idx[:above[-1] + 2] if above.size and above[-1] + 1 < down_idx.size else down_idx
    m_up = (np.r_[seat, model["sigma_v"][up]], np.r_[0.0, eps_a[up]])
    m_down = (np.r_[model["sigma_v"][up][-1], model["sigma_v"][down_idx]], np.r_[eps_a[up][-1], eps_a[down_idx]])
    k0_at = lambda level: float(np.interp(level, model["sigma_v"][up], model["K0"][up]))  # noqa: E731
    unload_interval = (float(unload_s[1]), top)
    summary = {
        "posterior": {"file": source.resolve().relative_to(ROOT).as_posix()
                      if source.resolve().is_relative_to(ROOT) else str(source), **mean},
        "law": "linear" if args.hertz is None else f"hertz-mindlin, G = {args.hertz:g} Pa, nu = 0.2",
        "critical_state": json.loads((args.calibration / "posterior.json").read_text()).get("critical_state")
        if args.calibration is not None else None,
        "seating_stress_Pa": seat,
        "constrained_modulus_low_Pa": {"interval": LOW, "model": modulus(*m_up, LOW), "data": modulus(load_s, load_e, LOW)},
        "constrained_modulus_high_Pa": {"interval": HIGH, "model": modulus(*m_up, HIGH), "data": modulus(load_s, load_e, HIGH)},
        "unloading_modulus_Pa": {"interval": unload_interval, "model": modulus(*m_down, unload_interval),
                                 "data": modulus(unload_s, unload_e, unload_interval)},
        "eps_a_at_top": {"stress_Pa": top, "model": strain_at(*m_up, top), "data": float(load_e[-1])},
        "eps_a_after_unloading": {"stress_Pa": bottom, "model": strain_at(*m_down, bottom), "data": float(unload_e[-1])},
        "K0_model": {"80kPa": k0_at(80e3), "top": k0_at(top), "after_unloading": float(np.interp(
            bottom, model["sigma_v"][down_idx][::-1], model["K0"][down_idx][::-1]))},
        "K0_jaky_repose": 1.0 - math.sin(math.radians(REPOSE_DEG)),
        "rms_eps_a_loading": rms_strain(m_up, load_s, load_e),
        "rms_eps_a_unloading": rms_strain(m_down, unload_s, unload_e),
    }
    for key in ("model", "data"):
        summary["unloading_modulus_Pa"][f"ratio_to_loading_{key}"] = (
            summary["unloading_modulus_Pa"][key] / modulus(*(m_up if key == "model" else (load_s, load_e)), unload_interval))
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"posterior mean of {source}: " + ", ".join(f"{k} {v:.4g}" for k, v in mean.items())
          + (f", alpha0_spread {mean['alpha0_spread']:.2f} deg" if "alpha0_spread" in mean else "")
          + f"; law: {summary['law']}; seated at {seat:g} Pa")
    print("quantity                                   model        data")
    for label, key in (("M, 40-80 kPa [MPa]", "constrained_modulus_low_Pa"), ("M, 0.6-1.2 MPa [MPa]", "constrained_modulus_high_Pa"),
                       ("unloading M, 1.2-0.6 MPa [MPa]", "unloading_modulus_Pa")):
        print(f"{label:40s} {summary[key]['model'] / 1e6:10.3g} {summary[key]['data'] / 1e6:10.3g}")
    u = summary["unloading_modulus_Pa"]
    print(f"{'unloading / loading M, 0.6-1.2 MPa':40s} {u['ratio_to_loading_model']:10.3g} {u['ratio_to_loading_data']:10.3g}")
    print(f"{'eps_a at 1.2 MPa [%]':40s} {100 * summary['eps_a_at_top']['model']:10.3g} {100 * summary['eps_a_at_top']['data']:10.3g}")
    print(f"{'eps_a after unloading to 10 kPa [%]':40s} {100 * summary['eps_a_after_unloading']['model']:10.3g} "
          f"{100 * summary['eps_a_after_unloading']['data']:10.3g}")
    print(f"{'RMS d eps_a at the measured stresses, loading [%]':40s} {100 * summary['rms_eps_a_loading']:10.3g}")
    print(f"{'RMS d eps_a at the measured stresses, unloading [%]':40s} {100 * summary['rms_eps_a_unloading']:10.3g}")
    k0 = summary["K0_model"]
    print(f"K0 of the model: {k0['80kPa']:.3f} at 80 kPa, {k0['top']:.3f} at {top / 1e6:g} MPa, {k0['after_unloading']:.3f} "
          f"after unloading to {bottom / 1e3:g} kPa; Jaky 1 - sin(angle of repose) {summary['K0_jaky_repose']:.3f} "
          f"(estimate; not measured)")
    draw(args.out / "oedometer.png", (load_s, load_e, unload_s, unload_e), m_up, m_down, model, up, down_idx,
         summary["K0_jaky_repose"], summary["law"] + (", critical-state rule" if summary["critical_state"] else ""))
    print(f"figure -> {args.out / 'oedometer.png'}; summary -> {args.out / 'summary.json'}")
    return 0


def draw(path: Path, data, m_up, m_down, model, up, down_idx, k0_jaky: float, law: str) -> None:
    """sigma_v [kPa] against eps_a [%] (data and model, loading and unloading) and K0 against sigma_v."""
    import matplotlib.pyplot as plt  # noqa: PLC0415

    load_s, load_e, unload_s, unload_e = data
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
    left.plot(100 * load_e, load_s / 1e3, "ko-", label="data, loading")
    left.plot(100 * unload_e, unload_s / 1e3, "ks--", mfc="none", label="data, unloading")
    left.plot(100 * m_up[1], m_up[0] / 1e3, "C0-", label="H-model, loading")
    left.plot(100 * m_down[1], m_down[0] / 1e3, "C1--", label="H-model, unloading")
    left.set_xlabel("vertical strain eps_a [%]")
    left.set_ylabel("vertical stress sigma_v [kPa]")
    left.legend(loc="upper left")
    right.plot(model["sigma_v"][up] / 1e3, model["K0"][up], "C0-", label="H-model, loading")
    right.plot(model["sigma_v"][down_idx] / 1e3, model["K0"][down_idx], "C1--", label="H-model, unloading")
    right.axhline(k0_jaky, color="k", ls=":", label="1 - sin(angle of repose) (estimate)")
    right.set_xscale("log")
    right.set_xlabel("vertical stress sigma_v [kPa]")
    right.set_ylabel("K0 = sigma_h / sigma_v [-]")
    right.legend()
    fig.suptitle(f"Dobrany sand, loose oedometer specimen (e0 0.996): data and the 3D H-model\n"
                 f"at the triaxial posterior mean ({law} law)", fontsize=10)
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
