"""python benchmarks/bench_dem_stepping.py [--orientations 360] [--repeats 3] [--quick] [--compare-one-thread]

Accuracy versus cost of the quasi-static DEM stepping (issue 10). For each test -- constant
volume and drained (sigma22 = p0), alpha0 = 55 deg, p0 = 2e5 and 5.85e6 N/m, isotropic
stage to p0 then shear to eps1 = --eps-max, increments --increment / --iso-increment -- it
runs the analytical backend and the DEM backend with a list of stepping settings (strain per
substep, fixed or adaptive, force tolerance, time step, damping) through the same programme
and prints, per setting:

- max |p_dem - p_ana| / p0 and max |q_dem - q_ana| / p0 over every increment;
- DEM substeps per cell and step call (trial calls of stress control included), step calls,
  unconverged cell-increments, or the error that stopped the run (stress control fails when
  the DEM response is too rough for the driver's stress tolerance);
- DEM wall time and its ratio to the analytical run.

With --robustness (--robustness-only: nothing else), drained runs over alpha0, p0 and
increment (H-cell, 360 orientations) and of cells with a fine grain (``FINES``) count, per
setting, how often the driver's stress control (``LoadingDefaults.stress_rtol``, or
--stress-rtol) converges on the DEM's response, the step calls per shear increment, and how
many increments it accepted at a jump of the response (``element_test.solver.StressControl.solve``).

Then the acceptance rows: DEM (``DemSettings()`` defaults) and analytical wall times side by
side, best of --repeats alternating runs each (the machine is shared: the load average is
printed), and the worst force error of the DEM against the committed YADE cases
(tests/data/yade) per case, as a fraction of the case's largest force.

Writes benchmarks/results/dem_stepping.json and docs/figures/dem_stepping.png (error
against substeps per cell-increment, one panel per test). Compression positive.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import time
import warnings
from dataclasses import asdict, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from homogenization.element_test import driver, programme as programmes
from homogenization.output import figures
from homogenization.output.figure_style import apply_style, GRID, number
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.core.provenance import git_revision

ROOT = Path(__file__).resolve().parent.parent
YADE_DIR = ROOT / "tests" / "data" / "yade"
ALPHA0_DEG = 55.0
PRESSURES = (2e5, 5.85e6)
DEFAULT = DemSettings()
DEFAULT_NAME = "defaults: tol 1e-6, dt 0.6, damping 0.7"
SETTINGS = {
    "fixed 2.5e-7, dt 0.2, damping 0.5 (issue-4 rate)": dict(
        strain_per_substep=2.5e-7, refined_strain_per_substep=2.5e-7, dt_factor=0.2, damping=0.5),
    DEFAULT_NAME: {},
    "fixed 2.5e-6": dict(strain_per_substep=2.5e-6, refined_strain_per_substep=2.5e-6),
    "fixed 2.5e-5": dict(strain_per_substep=2.5e-5, refined_strain_per_substep=2.5e-5),
    "fixed 1e-4": dict(strain_per_substep=1e-4, refined_strain_per_substep=1e-4),
    "adaptive 1e-4/5e-6": dict(strain_per_substep=1e-4),
    "tol 1e-5": dict(force_tolerance=1e-5),
    "tol 1e-4": dict(force_tolerance=1e-4),
    "tol 1e-3": dict(force_tolerance=1e-3),
    "dt 0.4, damping 0.5": dict(dt_factor=0.4, damping=0.5),
    "dt 0.6, damping 0.6": dict(damping=0.6),
    "dt 0.8, damping 0.7": dict(dt_factor=0.8),
    "dt 0.9, damping 0.8": dict(dt_factor=0.9, damping=0.8),
}
"""Name -> DemSettings overrides of the defaults (every other field: DemSettings()); the stepping
is the kernel's (adaptive rate, predicted free grains), "fixed" rows without rate adaptation."""
ROBUSTNESS = {DEFAULT_NAME: {}, "tol 1e-5": dict(force_tolerance=1e-5), "tol 1e-4": dict(force_tolerance=1e-4)}
"""Settings whose stress control is tried on --robustness (drained runs over alpha0, p0, increment)."""
FINES = (("hcell-fines:alpha0=50,ratio=0.8", 1e-4), ("hcell-fines:alpha0=50,ratio=0.8", 1e-3),
         ("hcell-fines:alpha0=50,ratio=0.7", 1e-4), ("hcell-fines:alpha0=55,ratio=0.76", 1e-4))
"""Drained runs of cells with a fine grain (p0 = 2e5, 72 orientations) also tried on --robustness:
mesostructure spec and shear increment."""


def programme(p0: float, drained: bool, args: argparse.Namespace) -> tuple:
    return programmes.biaxial(p0, args.eps_max, args.increment, iso_increment=args.iso_increment, drained=drained)


def timed(model, prog, n_orientations: int) -> tuple[driver.Record, float]:
    record, wall, _ = timed_cpu(model, prog, n_orientations)
    return record, wall


def timed_cpu(model, prog, n_orientations: int) -> tuple[driver.Record, float, float]:
    """The record, its wall time [s] and the CPU time of this process [s] (steadier under load)."""
    start, cpu = time.perf_counter(), time.process_time()
    record = driver.run(model, prog, mesostructure=h_cell(ALPHA0_DEG), n_orientations=n_orientations, progress=False)
    return record, time.perf_counter() - start, time.process_time() - cpu


def dem_model(settings: DemSettings, threads: int):
    """A DEM backend whose kernel is compiled and loaded (not timed)."""
    model = make_cell_model("dem", settings=settings, threads=threads)
    state = model.init_state(h_cell(ALPHA0_DEG), 2)
    model.step(state, np.full((2, 2), 1e-5))
    return model


def compare(ana: driver.Record, dem: driver.Record, p0: float, n_orientations: int) -> dict:
    n = min(ana.n_increments, dem.n_increments)
    calls = dem.newton_iterations[:n].sum()
    return {"max_dp_over_p0": float(np.abs(dem.p[:n] - ana.p[:n]).max() / p0),
            "max_dq_over_p0": float(np.abs(dem.q[:n] - ana.q[:n]).max() / p0),
            "substeps_per_cell_call": float(dem.diagnostics["substeps_all_calls"][:n].sum() / calls / n_orientations),
            "step_calls": int(calls), "analytical_step_calls": int(ana.newton_iterations[:n].sum()),
            "unconverged": float(np.nansum(dem.diagnostics["n_unconverged_all_calls"][:n]))}


def yade_errors(settings: DemSettings) -> dict[str, float]:
    """Worst |N1|, |N2|, |T1| error of the DEM cell against each YADE case / its largest force."""
    names = sorted(p.name.removesuffix(".path.csv") for p in YADE_DIR.glob("*.path.csv"))
    model = make_cell_model("dem", contact_law=ContactLaw(), settings=settings, threads=1)
    errors = {}
    for name in names:
        path = np.loadtxt(YADE_DIR / f"{name}.path.csv", delimiter=",", skiprows=1, ndmin=2)
        yade = np.genfromtxt(YADE_DIR / f"{name}.yade.csv", delimiter=",", names=True)
        alpha0 = json.loads((YADE_DIR / f"{name}.json").read_text())["alpha0_deg"]
        state = model.init_state(h_cell(alpha0), 1)
        worst = 0.0
        for row, d_eps in enumerate(path):
            state, _ = model.step(state, d_eps[None, :])
            obs = model.observables(state)
            worst = max(worst, *(abs(float(obs[k][0]) - float(yade[k][row])) for k in ("N1", "N2", "T1")))
        scale = max(float(np.abs(yade[k]).max()) for k in ("N1", "N2", "T1"))
        errors[name] = worst / scale
    return errors


def plot(rows: list[dict], path: Path) -> None:
    tests = list(dict.fromkeys(r["test"] for r in rows))
    n_col = 2
    n_row = -(-len(tests) // n_col)
    fig = Figure(figsize=(11, 4.2 * n_row), layout="constrained")
    axes = fig.subplots(n_row, n_col, sharex=True, sharey=True, squeeze=False)
    for ax, test in zip(axes.flat, tests):
        failed = [r["name"] for r in rows if r["test"] == test and "error" in r]
        for r in (r for r in rows if r["test"] == test and "error" not in r):
            err = max(r["max_dp_over_p0"], r["max_dq_over_p0"])
            marker = "o" if r["name"].startswith("fixed") else "s"
            color = "C3" if r["name"] == DEFAULT_NAME else ("C0" if marker == "o" else "C1")
            is_default = r["name"] == DEFAULT_NAME
            ax.loglog(r["substeps_per_cell_call"], err, marker, color=color, markersize=9 if is_default else 6,
                      zorder=3 if is_default else 2)
            ax.annotate(r["name"].split(" (")[0], (r["substeps_per_cell_call"], err), fontsize=6)
        ax.axhline(1e-3, color="k", lw=0.8, ls="--")
        name = re.sub(r"p0 = (\S+)", lambda m: f"$p_0 = {number(float(m[1]))}$ N/m", test)  # keys as in the JSON
        ax.set_title(name + (f" ({len(failed)} settings: stress control failed)" if failed else ""), fontsize=9)
        ax.set_xlabel("DEM substeps per cell and step call")
        ax.set_ylabel(r"$\max(|\Delta p|, |\Delta q|)/p_0$ against the analytical cell [-]")
        ax.grid(True, which="both", **GRID)
    fig.suptitle("DEM stepping, 360 orientations, increment $10^{-4}$: accuracy against cost\n"
                 "(circles: fixed strain per substep, squares: adaptive, red: defaults; dashed: $10^{-3}$)", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    figures.save_figure(apply_style(fig), path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[2],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--orientations", type=int, default=360)
    parser.add_argument("--increment", type=float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--iso-increment", type=float, default=1e-4, help="isotropic increment per component [-]")
    parser.add_argument("--eps-max", type=float, default=0.2)
    parser.add_argument("--threads", type=int, default=2, help="CPU threads of the DEM")
    parser.add_argument("--compare-one-thread", action="store_true",
                        help="also time the DEM on one thread in the acceptance runs (alternating)")
    parser.add_argument("--repeats", type=int, default=3, help="alternating runs for the acceptance timings")
    parser.add_argument("--quick", action="store_true", help="acceptance rows and YADE only, no sweep")
    parser.add_argument("--robustness", action="store_true",
                        help="also: drained runs to 10 %% at alpha0 40/55/70, both p0, increments 1e-4 and 5e-4, "
                             "per setting of ROBUSTNESS: how many finish (stress control converges)")
    parser.add_argument("--stress-rtol", type=float, default=None,
                        help="driver's stress tolerance of the --robustness runs [-] (default: the driver's)")
    parser.add_argument("--robustness-only", action="store_true", help="only the --robustness runs")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "dem_stepping.json")
    parser.add_argument("--figure", type=Path, default=ROOT / "docs" / "figures" / "dem_stepping.png")
    args = parser.parse_args()
    if args.orientations < 1 or args.repeats < 1 or not 0 < args.increment < 1 or not 0 < args.iso_increment < 1:
        parser.error("--orientations and --repeats must be >= 1, increments in (0, 1)")

    analytical = make_cell_model("analytical")
    print(f"load average {os.getloadavg()} on {os.cpu_count()} cpus; N = {args.orientations}, increment "
          f"{args.increment:g} (iso {args.iso_increment:g}), eps1 to {args.eps_max:g}, DEM threads {args.threads}; "
          f"defaults {asdict(DEFAULT)}", flush=True)

    # acceptance: constant volume, default settings, best of alternating repeats
    acceptance = []
    default_model = dem_model(DEFAULT, args.threads)
    one_thread = dem_model(DEFAULT, 1) if args.compare_one_thread else None
    for p0 in () if args.robustness_only else PRESSURES:
        prog = programme(p0, False, args)
        t_ana, t_dem, c_ana, c_dem, t_one = [], [], [], [], []
        for _ in range(args.repeats):
            ana, t, c = timed_cpu(analytical, prog, args.orientations)
            t_ana.append(t)
            c_ana.append(c)
            dem, t, c = timed_cpu(default_model, prog, args.orientations)
            t_dem.append(t)
            c_dem.append(c)
            if one_thread is not None:
                t_one.append(timed(one_thread, prog, args.orientations)[1])
        row = {"p0": p0, "time_analytical_s": min(t_ana), "time_dem_s": min(t_dem),
               "times_analytical_s": t_ana, "times_dem_s": t_dem, "cpu_analytical_s": min(c_ana),
               "cpu_dem_s": min(c_dem), **compare(ana, dem, p0, args.orientations)}
        row["ratio"] = row["time_dem_s"] / row["time_analytical_s"]
        row["cpu_ratio"] = row["cpu_dem_s"] / row["cpu_analytical_s"]
        if t_one:
            row.update(times_dem_one_thread_s=t_one, ratio_one_thread=min(t_one) / row["time_analytical_s"])
            print(f"   DEM on one thread: {min(t_one):.3f} s, ratio {row['ratio_one_thread']:.2f}", flush=True)
        acceptance.append(row)
        print(f"ACCEPTANCE constant volume p0 = {p0:g}: analytical {row['time_analytical_s']:.3f} s, DEM "
              f"{row['time_dem_s']:.3f} s (best of {args.repeats}), ratio {row['ratio']:.2f} (CPU time "
              f"{row['cpu_analytical_s']:.3f} / {row['cpu_dem_s']:.3f} s, ratio {row['cpu_ratio']:.2f}) | max|dp|/p0 "
              f"{row['max_dp_over_p0']:.2e} max|dq|/p0 {row['max_dq_over_p0']:.2e} | substeps/cell/call "
              f"{row['substeps_per_cell_call']:.2f} | unconverged {row['unconverged']:.0f} | load {os.getloadavg()[0]:.2f}",
              flush=True)
    yade = {} if args.robustness_only else yade_errors(DEFAULT)
    print("YADE worst force error / case max force (defaults): "
          + ", ".join(f"{k} {v:.1e}" for k, v in yade.items()), flush=True)

    rows = []
    if not (args.quick or args.robustness_only):
        for drained in (False, True):
            for p0 in PRESSURES:
                test = f"{'drained' if drained else 'constant volume'}, p0 = {p0:g}"
                prog = programme(p0, drained, args)
                ana, t_ana = timed(analytical, prog, args.orientations)
                print(f"-- {test}: analytical {t_ana:.2f} s, {ana.newton_iterations.sum()} step calls", flush=True)
                for name, overrides in SETTINGS.items():
                    settings = replace(DEFAULT, **overrides)
                    row = {"test": test, "name": name, "settings": asdict(settings), "time_analytical_s": t_ana}
                    try:
                        dem, t_dem = timed(dem_model(settings, args.threads), prog, args.orientations)
                    except driver.ControlError as error:
                        row["error"] = str(error)
                        print(f"   {name:<48} FAILED: {error}", flush=True)
                        rows.append(row)
                        continue
                    row.update(time_dem_s=t_dem, ratio=t_dem / t_ana, **compare(ana, dem, p0, args.orientations))
                    rows.append(row)
                    print(f"   {name:<48} dp {row['max_dp_over_p0']:.1e} dq {row['max_dq_over_p0']:.1e} | "
                          f"substeps/cell/call {row['substeps_per_cell_call']:7.2f} | calls {row['step_calls']} | "
                          f"DEM {t_dem:6.2f} s ({row['ratio']:.1f}x) | unconverged {row['unconverged']:.0f}", flush=True)
        plot(rows, args.figure)
        print(f"-> {args.figure}")
    robustness = {}
    if args.robustness or args.robustness_only:
        rtol = {} if args.stress_rtol is None else {"stress_rtol": args.stress_rtol}
        for name, overrides in ROBUSTNESS.items():
            model, failures, runs, calls, jumps = dem_model(replace(DEFAULT, **overrides), args.threads), [], 0, [], 0
            cases = [(h_cell(alpha0), f"alpha0 {alpha0:g}", p0, increment, args.orientations)
                     for alpha0 in (40.0, 55.0, 70.0) for p0 in PRESSURES for increment in (1e-4, 5e-4)]
            cases += [(resolve_mesostructure(spec), spec, 2e5, increment, 72) for spec, increment in FINES]
            for meso, label, p0, increment, n_orientations in cases:
                runs += 1
                prog = programmes.biaxial(p0, 0.1, increment, iso_increment=args.iso_increment,
                                       drained=True)
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", RuntimeWarning)  # jumps are counted below
                        record = driver.run(model, prog, mesostructure=meso, n_orientations=n_orientations,
                                            progress=False, **rtol)
                    calls.append(float(record.newton_iterations[record.stage == "shear"].mean()))
                    jumps += int(np.nansum(record.diagnostics.get("stress_control_jump", np.zeros(1))))
                except driver.ControlError as error:
                    failures.append(f"{label}, p0 {p0:g}, increment {increment:g}: {error}")
            robustness[name] = {"runs": runs, "failures": failures, "step_calls_per_shear_increment": calls,
                                "stress_control_jumps": jumps}
            print(f"ROBUSTNESS {name}: {runs - len(failures)} of {runs} drained runs finish "
                  f"({len(cases) - len(FINES)} H-cell, {len(FINES)} with a fine grain); step calls per shear increment "
                  f"{' '.join(f'{c:.2f}' for c in calls)}; stress-control jumps accepted {jumps}"
                  + "".join(f"\n   failed: {f}" for f in failures), flush=True)
    result = {"machine": {"date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                          "cpus": os.cpu_count(), "load_average_end": os.getloadavg(), "git_revision": git_revision()},
              "options": vars(args) | {"json": str(args.json), "figure": str(args.figure)},
              "defaults": asdict(DEFAULT), "acceptance": acceptance, "yade": yade, "sweep": rows,
              "robustness": robustness}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"-> {args.json}")


if __name__ == "__main__":
    main()
