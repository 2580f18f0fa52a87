"""python -m homogenization.sweep --mesostructure hcell,hcell-fines:ratio=0.76 --alpha0 50,55 --p0 2e5,5.85e6 --backend dem --eps-max 0.15 --increment 1e-4 --orientations 72 --out DIR

Biaxial tests (as ``homogenization.biaxial``) over the Cartesian product of the comma lists
--mesostructure x --alpha0 x --p0 x --backend. A mesostructure is a TOML/JSON file or a builder
spec (``warp_hcell.mesostructures.builders``); a spec without alpha0 is built at each --alpha0,
a file or a spec with alpha0 makes one case per p0 and backend. A backend that refuses a
mesostructure (``homogenization.backends.mesostructure_refusal``) skips it; the skipped
combinations are listed.

ANN models (--model, repeatable; a model records its mesostructure's sha256):
``--model MESOSTRUCTURE=PATH`` gives the model of one mesostructure of --mesostructure;
``--model PATH`` is used where its recorded mesostructure is the case's. The plain H-cell runs
on its own model, else the single bare --model (a model of an H-cell: other grains are refused),
else the installed model. A fines cell without a model is an error before any case runs.

--erode-at EPS (dem): grains free along every axis (fines) are removed at eps1 = EPS
(``warp_hcell.dem.erosion``); one increment (stage ``erode``) records the relaxation, then the
test continues (stage ``eroded``) to --eps-max.

Output:

- DIR/cases/<case>/{run.h5, curve.csv, cambridge.png}: the files ``biaxial`` writes.
- DIR/summary.csv: one row per case (``SUMMARY_COLUMNS``): stresses [N/m], strains [-],
  compression positive, eps1 from the end of the isotropic stage; peak_q the largest q,
  first_peak_q the first maximum after which q falls by more than
  ``homogenization.sweeps.case.SOFTENING_DROP`` p0 (NaN if none); p_at_5pct.. p at eps1 = 5,
  10, 15 %; counts the backend's rules that fired (``case.fired_counts``, e.g. ``n_alpha_limit=373``).
- DIR/summary.png: the q/p0 and p/p0 curves and (p/p0, q/p0) paths of every case.
- DIR/sweep.json: the options of the sweep.

Cases are planned by ``homogenization.sweeps.plan``, computed by ``homogenization.sweeps.case``
as tasks of ``warp_hcell.core.execution`` (this process, --workers N, or --scheduler ADDRESS;
docs/distributed.md); this process writes every file, so results do not depend on the execution.
Each case's folder is written as a unit, under a lock of DIR (a second sweep on DIR exits 2);
rerunning keeps finished cases (same parameters in run.h5, the mesostructure's geometry
included); a case holding other parameters is an error unless --overwrite. Bad input is one
line on stderr, exit code 2, before any case runs; cases that fail while running are listed,
exit code 1. Ctrl-C or kill: one line, exit 130, and the same command resumes.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
from matplotlib.figure import Figure

from homogenization.element_test import driver
from homogenization.output import figures, io, run_labels
from homogenization.cli.options import (
    ISO_TO_SHEAR_INCREMENT,
    add_orientations_argument,
    add_threads_argument,
    add_uncertified_argument,
    backend_list,
    command_parser,
    refuse_uncertified_file,
)
from homogenization.output.figure_style import LABELS
from homogenization.cli.run_files import shear_iso_increment
from homogenization.sweeps.case import case_task, fired_counts, summarise
from homogenization.sweeps.plan import Case, ModelChoice, plan
from warp_hcell.mesostructures.builders import (
    MESOSTRUCTURE_HELP,
    mesostructure_list_arg,
)
from warp_hcell.core.cli import (
    UserError,
    alpha0_deg,
    axial_strain,
    positive_float,
    positive_int,
    run_main,
    say,
    set_verbosity,
    task_setup,
    writing_to,
)
from warp_hcell.core.files import atomic_write, check_output_path, output_folder, output_lock
from warp_hcell.core.execution import make_execution, SchedulerUnreachable
from warp_hcell.core.parameters import CellDefaults, DatabaseSettings, LoadingDefaults

COARSE_INCREMENT = DatabaseSettings.probe_max
"""Shear increments above this [-] run with a warning (as ``hmodel biaxial``'s)."""
CASES_DIR = "cases"
SUMMARY_FILE = "summary.csv"
SUMMARY_FIGURE = "summary.png"
SWEEP_FILE = "sweep.json"
FIGURE_FILE = "cambridge.png"
SUMMARY_COLUMNS = (
    "mesostructure", "backend", "alpha0", "p0", "peak_q", "eps1_at_peak", "p_at_peak", "p_end", "q_end", "eps1_end",
    "p_at_5pct", "p_at_10pct", "p_at_15pct", "first_peak_q", "eps1_at_first_peak", "p_at_first_peak",
    "erode_at", "n_grains", "n_unconverged", "counts", "case",
)
"""Columns of summary.csv, in order."""


def float_list(check: Callable[[str], float]) -> Callable[[str], list[float]]:
    """argparse type: comma list of values each checked by ``check`` (duplicates dropped)."""
    def parse(text: str) -> list[float]:
        values = [check(piece.strip()) for piece in text.split(",") if piece.strip()]
        if not values:
            raise argparse.ArgumentTypeError("empty list")
        return list(dict.fromkeys(values))
    parse.__name__ = f"{check.__name__}_list"
    return parse


def erode_strain(text: str) -> float:
    """argparse type: axial strain of erosion [-], in (0, 1)."""
    value = positive_float(text)
    if value >= 1.0:
        raise argparse.ArgumentTypeError(f"{text} must be < 1")
    return value


def model_arg(text: str) -> ModelChoice:
    """argparse type: ``PATH`` or ``MESOSTRUCTURE=PATH`` (split at the last ``=``)."""
    key, sep, path = str(text).rpartition("=")
    if not sep:
        return ModelChoice(None, Path(text.strip()))
    if not key.strip() or not path.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not PATH or MESOSTRUCTURE=PATH")
    return ModelChoice(key.strip(), Path(path.strip()))


def build_parser() -> argparse.ArgumentParser:
    """Parser of the sweep command (defaults read from warp_hcell.core.parameters)."""
    cell, load = CellDefaults(), LoadingDefaults()
    parser = command_parser("homogenization.sweep", "Biaxial tests over the Cartesian product of mesostructures, "
                                                    "alpha0, p0 and backends.")
    parser.add_argument("--mesostructure", type=mesostructure_list_arg, action="extend", default=None,
                        help="comma list (or repeat the flag); each item a " + MESOSTRUCTURE_HELP
                        + "; a KEY=VALUE item continues the spec before it. None: hcell")
    parser.add_argument("--alpha0", type=float_list(alpha0_deg), default=f"{cell.alpha0_deg:g}",
                        help="comma list of initial opening angles [deg] for specs without their own alpha0")
    parser.add_argument("--p0", type=float_list(positive_float), default=f"{cell.p0:g}",
                        help="comma list of confining pressures [N/m]")
    parser.add_argument("--backend", type=backend_list, default="dem", help="comma list of cell models")
    parser.add_argument("--eps-max", type=axial_strain, default=load.eps_max,
                        help="axial strain at the end of the shear stage, counted from its start [-]")
    parser.add_argument("--increment", type=positive_float, default=load.increment,
                        help="axial strain increment of the shear stage [-], <= --eps-max")
    parser.add_argument("--iso-increment", type=positive_float, default=argparse.SUPPRESS,
                        help=f"strain increment per component of the isotropic stage [-] "
                             f"(default: {ISO_TO_SHEAR_INCREMENT:g} x --increment)")
    add_orientations_argument(parser, cell.n_orientations)
    parser.add_argument("--drained", action="store_true", help="hold sigma22 = p0 during shear instead of constant volume")
    parser.add_argument("--stress-rtol", type=positive_float, default=load.stress_rtol,
                        help="relative tolerance of stress-controlled components (--drained, landing on p0) [-]")
    parser.add_argument("--erode-at", type=erode_strain, default=None,
                        help="remove the grains free along n and t (fines) at this eps1 [-] (dem; None: no erosion)")
    parser.add_argument("--workers", type=positive_int, default=None,
                        help="cases run at once: worker processes of a local Dask cluster, 1: in this process "
                             "(None: the cores available; the results do not depend on it)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run the cases on this Dask scheduler (e.g. tcp://host:8786) instead of locally")
    add_threads_argument(parser, "CPU threads of the DEM within each case", 1)
    parser.add_argument("--model", type=model_arg, action="append", default=None, metavar="[MESOSTRUCTURE=]PATH",
                        help="ANN model (ann only; repeat the flag): MESOSTRUCTURE=PATH for one item of "
                             "--mesostructure, PATH for the mesostructure it was trained on (or the plain H-cell); "
                             "None: the installed model (plain H-cell)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (rerun to resume)")
    add_uncertified_argument(parser)
    return parser


# -- one case's files ----------------------------------------------------------------------------


def _summary_row(case: Case, record: driver.Record) -> dict[str, Any]:
    prm = case.parameters
    return {"mesostructure": case.source, "backend": case.backend, "alpha0": case.alpha0, "p0": case.p0,
            **summarise(record, case.p0), "erode_at": prm["erode_at"] if prm["erode_at"] is not None else math.nan,
            "n_grains": prm["n_grains"], "counts": fired_counts(record), "case": case.folder}


def write_case(case: Case, record: driver.Record, out: Path, seed: int) -> dict[str, Any]:
    """Write the folder of a computed case (run.h5, curve.csv, figure) as a unit (``output_folder``: an interrupted
    write leaves the case's previous folder whole); returns its summary row."""
    prm = case.parameters
    with output_folder(Path(out) / CASES_DIR / case.folder) as work:
        io.write_run(work, record, parameters=prm, seed=seed)
        figures.save_figure(figures.overlay_figure([figures.Run(record, prm)]), work / FIGURE_FILE)
    return _summary_row(case, record)


def stored_row(case: Case, out: Path, *, overwrite: bool) -> dict[str, Any] | None:
    """Summary row of a finished case (its three files, with the same parameters in run.h5), None if it must run.

    Raises:
        UserError: the folder holds a run with other parameters and not ``overwrite``.
    """
    folder = out / CASES_DIR / case.folder
    run_file = folder / io.RUN_FILE
    if not all((folder / name).is_file() for name in (io.RUN_FILE, io.CURVE_FILE, FIGURE_FILE)):
        return None
    try:
        stored = io.read_run(run_file)
    except UserError:
        if overwrite:
            return None
        raise
    if stored.attrs["parameters"] == json.loads(json.dumps(case.parameters)):
        return _summary_row(case, stored.record)
    if overwrite:
        return None
    differ = sorted(k for k in set(case.parameters) | set(stored.attrs["parameters"])
                    if json.loads(json.dumps(case.parameters.get(k))) != stored.attrs["parameters"].get(k))
    raise UserError(f"{folder} holds a run with other {', '.join(differ)}; pass --overwrite or choose another --out")


def run_cases(cases: Sequence[Case], out: Path, seed: int, execution: Any,
              report: Callable[[Case, float | None, str | None], None]) -> tuple[dict[str, dict], dict[str, str]]:
    """Run ``cases`` on ``execution`` (``warp_hcell.core.execution``); write each case as it comes back and say the
    warnings it raised, one line each naming the case.

    Returns:
        (rows, failures): summary rows and error messages, keyed by case folder.
    """
    rows: dict[str, dict] = {}
    failures: dict[str, str] = {}
    for case, (record, seconds, error, raised) in execution.map(case_task, None, cases):
        for line in raised:
            print(f"warning: {case.folder}: {line}", file=sys.stderr)
        if error is not None:
            failures[case.folder] = error
            report(case, None, error)
            continue
        rows[case.folder] = write_case(case, record, out, seed)
        report(case, seconds, None)
    return rows, failures


# -- summary -------------------------------------------------------------------------------------

def write_summary(path: Path, rows: Iterable[dict[str, Any]]) -> Path:
    """summary.csv, one row per case in ``rows`` order (floats with 17 significant digits)."""
    lines = [",".join(SUMMARY_COLUMNS)]
    for row in rows:
        lines.append(",".join(_cell(row[c]) for c in SUMMARY_COLUMNS))
    with atomic_write(Path(path)) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return Path(path)


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.17g}"
    text = str(value)
    return f'"{text}"' if ("," in text or '"' in text) else text


def read_summary(path: Path) -> list[dict[str, Any]]:
    """summary.csv back as rows (numeric columns as float)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    text_columns = {"mesostructure", "backend", "counts", "case"}
    return [{k: (v if k in text_columns else float(v)) for k, v in row.items()} for row in rows]


def summary_figure(path: Path, cases: Sequence[Case], out: Path) -> Path:
    """Write summary.png (``make_summary_figure``) of ``cases`` stored under ``out``; returns ``path``."""
    runs = [figures.Run(io.read_run(out / CASES_DIR / case.folder / io.RUN_FILE).record, case.parameters)
            for case in cases]
    return figures.save_figure(make_summary_figure(runs), path)


def make_summary_figure(runs: Sequence[figures.Run]) -> Figure:
    """q/p0 and p/p0 against eps1 and the (p/p0, q/p0) path of every run; title and legend from their metadata."""
    title, labels = run_labels.split_labels([figures.describe_run(run) for run in runs])
    curves = []
    for colour, run, label in zip(plotting_colours(len(runs)), runs, labels):
        c = figures.shear_curve(run.record)
        p0 = figures.reference_pressure(run)
        curves.append((label, {"color": colour, "lw": 1.0},
                       ((100.0 * c.eps1, c.q / p0), (100.0 * c.eps1, c.p / p0), (c.p / p0, c.q / p0))))
    panels = ((LABELS["eps1"], LABELS["q/p0"], "deviator"), (LABELS["eps1"], LABELS["p/p0"], "mean stress"),
              (LABELS["p/p0"], LABELS["q/p0"], "stress path"))
    return figures.panel_figure(curves, panels, figsize=(15.0, 5.6),
                                title=f"sweep: {title} (compression positive)" if title else "sweep (compression positive)")


def plotting_colours(n: int) -> list:
    """n distinct colours: tab10 / tab20 up to 20, viridis beyond."""
    from matplotlib import colormaps

    if n <= 10:
        return [colormaps["tab10"](k) for k in range(n)]
    if n <= 20:
        return [colormaps["tab20"](k) for k in range(n)]
    return [colormaps["viridis"](x) for x in np.linspace(0.0, 0.9, n)]


# -- entry point ---------------------------------------------------------------------------------

def _prepare_out(out: Path, options: dict[str, Any], *, overwrite: bool) -> None:
    """Refuse a non-empty DIR that is not a sweep folder (unless --overwrite); write sweep.json."""
    if not (out / SWEEP_FILE).is_file():
        check_output_path(out, overwrite=overwrite)
    else:
        check_output_path(out / SWEEP_FILE, overwrite=True)
    with writing_to(out), atomic_write(out / SWEEP_FILE) as tmp:
        tmp.write_text(json.dumps(options, indent=1, sort_keys=True) + "\n")


def warn_outside_envelope(cases: Sequence[Case]) -> int:
    """One warning line on stderr where ann cases leave their model's certificate envelope
    (``ann_model.outside_envelope``, stored in each case's run.h5); returns how many do."""
    outside = [case for case in cases if case.backend == "ann" and case.parameters["ann_model"]["outside_envelope"]]
    if outside:
        phrases = dict.fromkeys(p for case in outside for p in case.parameters["ann_model"]["outside_envelope"])
        n_ann = sum(case.backend == "ann" for case in cases)
        print(f"warning: ann: {len(outside)} of {n_ann} ann case(s) run outside their model's certificate envelope: "
              f"{'; '.join(phrases)} (each case's run.h5: ann_model.outside_envelope)", file=sys.stderr)
    return len(outside)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command's arguments, --iso-increment resolved (``run_files.shear_iso_increment``); a warning line where
    the shear increments exceed ``COARSE_INCREMENT``.

    Raises:
        UserError: --device cuda without a dem or ann backend; increments the programme cannot take (one line).
    """
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    if args.device != "cpu" and not {"dem", "ann"} & set(args.backend):
        raise UserError("--device applies to --backend dem or ann only (analytical runs on the cpu)")
    args.iso_increment = shear_iso_increment(args, f": the shear stage would be one increment of {args.eps_max:g}")
    if args.increment > COARSE_INCREMENT:
        print(f"warning: shear increments of {args.increment:g} > {COARSE_INCREMENT:g}: coarse kinematics (~1 % of "
              f"p0 and more){'; the ANN extrapolates beyond its training probes' if 'ann' in args.backend else ''}",
              file=sys.stderr)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = parse_args(argv)
    out: Path = args.out
    cases, skipped = plan(args)
    for model in {case.parameters["backend_options"].get("model") for case in cases if case.backend == "ann"}:
        refuse_uncertified_file(model, args)
    warn_outside_envelope(cases)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder")
    with output_lock(out):
        rows = {case.folder: stored_row(case, out, overwrite=args.overwrite) for case in cases}
        todo = [case for case in cases if rows[case.folder] is None]
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        workers = min(args.workers or cores, max(len(todo), 1))
        try:
            execution = make_execution(workers, args.scheduler, setup=task_setup(args))
        except SchedulerUnreachable as exc:
            raise UserError(str(exc)) from None
        with execution:
            return _run(args, cases, skipped, rows, todo, execution)


def _run(args: argparse.Namespace, cases: list[Case], skipped: list[str], rows: dict[str, dict | None],
         todo: list[Case], execution: Any) -> int:
    out: Path = args.out
    options = {k: v for k, v in vars(args).items() if k not in ("out", "overwrite", "scheduler", "quiet", "verbose")}
    options["model"] = [f"{m.key}={m.path}" if m.key else str(m.path) for m in args.model or ()] or None
    options["mesostructure"] = [m.text for m in args.mesostructure] if args.mesostructure else None
    _prepare_out(out, options, overwrite=args.overwrite)
    say(*(f"skipped: {note}" for note in skipped))
    say(f"{len(cases)} cases: {len(cases) - len(todo)} finished before, {len(todo)} to run")
    others = sorted({p.name for p in (out / CASES_DIR).glob("*") if p.is_dir() and not p.name.startswith(".")}
                    - {case.folder for case in cases})
    if others:
        say(f"{len(others)} case folder(s) of other settings in {out / CASES_DIR} are not in this summary "
            f"(e.g. {others[0]})")

    def report(case: Case, seconds: float | None, error: str | None) -> None:
        state = f"failed: {error}" if error else f"{seconds:.1f} s"
        say(f"  {case.folder}: {state}")

    start = time.perf_counter()
    done, failures = run_cases(todo, out, args.seed, execution, report)
    elapsed = time.perf_counter() - start
    rows.update(done)
    finished = [case for case in cases if rows.get(case.folder) is not None]
    summary = write_summary(out / SUMMARY_FILE, (rows[case.folder] for case in finished))
    figure = summary_figure(out / SUMMARY_FIGURE, finished, out) if finished else None
    say(f"{len(todo)} cases run in {elapsed:.1f} s with {execution.n_workers} worker(s) -> {summary}"
        + (f", {figure}" if figure else ""))
    if failures:
        print(f"{len(failures)} case(s) failed: {', '.join(failures)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(run_main(main))
