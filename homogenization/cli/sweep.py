"""python -m homogenization.sweep --mesostructure hcell,hcell-fines:ratio=0.76 --alpha0 50,55 --p0 2e5,5.85e6 --backend dem --eps-max 0.15 --increment 1e-4 --orientations 72 --out DIR

Biaxial tests (isotropic compression to p0, then constant-volume or, with --drained,
sigma22 = p0 shear, as ``homogenization.biaxial``) over the Cartesian product of the lists
--mesostructure x --alpha0 x --p0 x --backend. Lists are comma separated; a mesostructure
is a TOML/JSON file or a builder spec (``warp_hcell.mesostructures.builders``; a spec without alpha0 is
built at each --alpha0, a file or a spec with alpha0 fixes its geometry and makes one case
per p0 and backend).

Every case's cells start from its mesostructure (``CellModel.init_state``). The dem and ann
backends run every mesostructure; a backend whose class refuses some
(``homogenization.backends.mesostructure_refusal``: the analytical backend models the
six-equal-grain H-cell only) skips the others, and the
skipped combinations are listed.

ANN models (--model, repeatable): a model is trained on one mesostructure and records its
sha256 (``training.checkpoint``). ``--model MESOSTRUCTURE=PATH`` gives the model of one
mesostructure of --mesostructure (the same text); ``--model PATH`` offers a model to every
mesostructure and is used where its recorded mesostructure is the case's (built at the case's
alpha0). The plain H-cell runs on any model of the H-cell's learning state (no sha256 check:
H-cell databases are explored from many alpha0, ``homogenization.backends.ann``) on its own
model, else the single bare --model, else the installed model. A fines cell without a model, or a model of another mesostructure, is an
error before any case runs.

--erode-at EPS (dem): in cases whose mesostructure has grains free along n and t (fines),
those grains are removed at eps1 = EPS (``warp_hcell.dem.erosion``); one increment at fixed eps11
(stage ``erode``: eps22 fixed too, or sigma22 brought back to p0 with --drained) records the
relaxation, then the test continues (stage ``eroded``) to --eps-max. The macro volume carries
on (V0 and J of the whole test).

Output:

- DIR/cases/<case>/{run.h5, curve.csv, cambridge.png}: the files ``biaxial`` writes, per case.
- DIR/summary.csv: one row per case (``SUMMARY_COLUMNS``): stresses [N/m] and strains [-],
  compression positive, eps1 counted from the end of the isotropic stage; peak_q is the
  largest q of the shear stages, first_peak_q the first maximum of q after which q falls by
  more than SOFTENING_DROP p0 (NaN if q never softens): the q peak of the instability
  analysis; p_at_5pct.. are p at eps1 = 5, 10, 15 % (NaN beyond the run).
- DIR/summary.png: q/p0 and p/p0 against eps1, and the (p/p0, q/p0) paths, of every case.
- DIR/sweep.json: the options of the sweep that made DIR.

Cases are tasks of ``warp_hcell.core.execution`` (as the database generator): in this process for
one worker, a Dask LocalCluster of --workers single-threaded processes, or the Dask scheduler
at --scheduler ADDRESS (a remote cluster; docs/distributed.md). A task computes one case and
returns its record; this process writes every file, so the workers need no shared file system
and the results do not depend on the execution (each case is computed alone). An unreachable
scheduler is one line, exit code 2, nothing written. Rerunning the command keeps finished cases (a case is
finished when its run.h5 holds the same parameters) and runs the others; a case folder holding
a run with other parameters is an error unless --overwrite. Bad input (unknown backend or
key, a mesostructure that does not build, unwritable DIR) is one line on stderr and exit
code 2, before any case runs; cases that fail while running are listed, exit code 1.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
import math
import os
import re
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from homogenization import driver, figures, io, loading, run_labels
from homogenization.cli.options import command_parser
from homogenization.backends import backend_class, make_cell_model, mesostructure_refusal
from homogenization.cli.biaxial import backend_list
from homogenization.figure_style import apply_style, figure_legend, GRID, LABELS
from warp_hcell.mesostructures.builders import (
    MESOSTRUCTURE_HELP,
    mesostructure_list_arg,
    MesostructureSource,
    parse_mesostructure,
)
from warp_hcell.core.cli import (
    UserError,
    alpha0_deg,
    positive_float,
    positive_int,
    run_main,
    say,
    set_verbosity,
    task_setup,
)
from warp_hcell.core.files import atomic_write, check_output_path
from warp_hcell.core.execution import make_execution, SchedulerUnreachable
from warp_hcell.mesostructures.files import describe, description_sha256
from warp_hcell.mesostructures.mesostructure import Mesostructure, MesostructureError
from warp_hcell.core.parameters import CellDefaults, ContactLaw, LoadingDefaults

CASES_DIR = "cases"
SUMMARY_FILE = "summary.csv"
SUMMARY_FIGURE = "summary.png"
SWEEP_FILE = "sweep.json"
FIGURE_FILE = "cambridge.png"
SUMMARY_COLUMNS = (
    "mesostructure", "backend", "alpha0", "p0", "peak_q", "eps1_at_peak", "p_at_peak", "p_end", "q_end", "eps1_end",
    "p_at_5pct", "p_at_10pct", "p_at_15pct", "first_peak_q", "eps1_at_first_peak", "p_at_first_peak",
    "erode_at", "n_grains", "n_unconverged", "case",
)
"""Columns of summary.csv, in order."""
STRAIN_MARKS = (0.05, 0.10, 0.15)
"""eps1 [-] of the p_at_<5|10|15>pct columns."""
SOFTENING_DROP = 0.01
"""Fall of q after a maximum, as a fraction of p0 [-], that makes it the first peak."""
ERODE_STAGE, ERODED_STAGE = "erode", "eroded"
"""Stage labels of the zero-strain removal increment and of the shear after it."""


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


@dataclass(frozen=True)
class ModelChoice:
    """One --model item: a model file, for one mesostructure (``key``, its text) or any (None)."""

    key: str | None
    path: Path


def model_arg(text: str) -> ModelChoice:
    """argparse type: ``PATH`` or ``MESOSTRUCTURE=PATH`` (split at the last ``=``)."""
    key, sep, path = str(text).rpartition("=")
    if not sep:
        return ModelChoice(None, Path(text.strip()))
    if not key.strip() or not path.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not PATH or MESOSTRUCTURE=PATH")
    return ModelChoice(key.strip(), Path(path.strip()))


class ModelTable:
    """The --model items, checked: which model file runs which ann case.

    Raises (constructor and ``for_case``):
        UserError: an unreadable model, a key that is not one of --mesostructure, a fines
            mesostructure without a model, a model of another mesostructure (one line).
    """

    def __init__(self, choices: Sequence[ModelChoice] | None, sources: Sequence[MesostructureSource]) -> None:
        from training.checkpoint import CheckpointError, read_metadata  # noqa: PLC0415 torch only for ann

        self.sha256: dict[Path, str] = {}
        self.keyed: dict[str, Path] = {}
        self.bare: list[Path] = []
        texts = {source.text: source for source in sources}
        for choice in choices or ():
            if not choice.path.is_file():
                raise UserError(f"--model {choice.path}: no such model file")
            try:
                self.sha256[choice.path] = read_metadata(choice.path)["mesostructure_sha256"]
            except CheckpointError as exc:
                raise UserError(str(exc)) from None
            if choice.key is None:
                self.bare.append(choice.path)
                continue
            key = self._source_text(choice.key, texts)
            if key in self.keyed and self.keyed[key] != choice.path:
                raise UserError(f"--model gives two models for {choice.key}")
            self.keyed[key] = choice.path

    @staticmethod
    def _source_text(key: str, texts: Mapping[str, MesostructureSource]) -> str:
        if key in texts:
            return key
        for text, source in texts.items():
            if source.kind is None and Path(key).resolve() == Path(text).resolve():
                return text
        raise UserError(f"--model {key}=...: {key} is not one of --mesostructure ({', '.join(texts)})")

    def for_case(self, source: MesostructureSource, meso: Any, plain: bool) -> Path | None:
        """The model file of an ann case (None: the installed model; plain H-cell only)."""
        sha = description_sha256(describe(meso))
        path = self.keyed.get(source.text)
        if path is None:
            path = next((p for p in self.bare if self.sha256[p] == sha), None)
        if path is None and plain:
            return self.bare[0] if len(self.bare) == 1 else None
        if path is None:
            raise UserError(f"no ANN model for mesostructure {source.text} ({meso.name}, sha256 {sha[:12]}); "
                            f"pass --model {source.text}=PATH with a model trained on it")
        if not plain and self.sha256[path] != sha:
            raise UserError(f"--model {path} was trained on mesostructure {self.sha256[path][:12]}, not on "
                            f"{source.text} ({sha[:12]}; the hash covers the spec text: generate with the same)")
        return path


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
    parser.add_argument("--eps-max", type=positive_float, default=load.eps_max,
                        help="axial strain at the end of the shear stage, counted from its start [-]")
    parser.add_argument("--increment", type=positive_float, default=load.increment, help="axial strain increment of the shear stage [-]")
    parser.add_argument("--iso-increment", type=positive_float, default=load.iso_increment,
                        help="strain increment per component of the isotropic stage [-]")
    parser.add_argument("--orientations", type=positive_int, default=cell.n_orientations, help="number N of cell orientations")
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
    parser.add_argument("--threads", type=positive_int, default=1, help="CPU threads of the DEM within each case")
    parser.add_argument("--model", type=model_arg, action="append", default=None, metavar="[MESOSTRUCTURE=]PATH",
                        help="ANN model (ann only; repeat the flag): MESOSTRUCTURE=PATH for one item of "
                             "--mesostructure, PATH for the mesostructure it was trained on (or the plain H-cell); "
                             "None: the installed model (plain H-cell)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (rerun to resume)")
    return parser


@dataclass(frozen=True)
class Case:
    """One run of the sweep; everything a worker needs (picklable, plain values).

    Attributes:
        source: mesostructure text (spec or file).
        backend: backend name.
        alpha0: opening angle [deg] passed to the driver (NaN for a file that is not a plain H-cell).
        p0: confining pressure [N/m].
        folder: case folder.
        parameters: the run parameters written to run.h5 (JSON-compatible); their equality
            decides whether a stored run is this case.
        options: backend options that do not change results (threads).
    """

    source: str
    backend: str
    alpha0: float
    p0: float
    folder: str
    parameters: dict[str, Any]
    options: dict[str, Any]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+-]+", "_", text).strip("_") or "case"


def plan(args: argparse.Namespace) -> tuple[list[Case], list[str]]:
    """Cases of the product (mesostructures built and validated) and the skipped combinations.

    Raises:
        UserError: a mesostructure that does not build, an option no case takes (one line).
    """
    sources: list[MesostructureSource] = args.mesostructure or mesostructure_list_arg("hcell")
    sources = list({s.text: s for s in sources}.values())
    law = ContactLaw()
    if args.model is not None and "ann" not in args.backend:
        raise UserError("--model applies to --backend ann only")
    models = ModelTable(args.model, sources) if "ann" in args.backend else None
    cases: list[Case] = []
    skipped: list[str] = []
    for source in sources:
        alphas = args.alpha0 if source.takes_alpha0 else [source.fixed_alpha0]
        for alpha0 in alphas:
            try:
                meso = source.build(alpha0)
            except MesostructureError as exc:
                raise UserError(str(exc)) from None
            plain = _closed_form_cell(meso)
            erodible = bool(np.any(~meso.driven.any(axis=1)))
            for p0 in args.p0:
                for backend in args.backend:
                    refusal = mesostructure_refusal(backend, meso)
                    if refusal is not None:
                        skipped.append(f"{backend} x {source.text}: {refusal}")
                        continue
                    erode_at = args.erode_at if erodible else None
                    if erode_at is not None and backend != "dem":
                        raise UserError(f"--erode-at needs --backend dem; {backend} cannot remove grains of {source.text}")
                    if erode_at is not None and erode_at >= args.eps_max:
                        raise UserError(f"--erode-at {erode_at:g} must be below --eps-max {args.eps_max:g}")
                    case_alpha0 = plain[0] if plain is not None else (float("nan") if alpha0 is None else float(alpha0))
                    radius = plain[1] if plain is not None else CellDefaults.radius
                    model = models.for_case(source, meso, plain is not None) if backend == "ann" else None
                    parameters = {
                        "backend": backend,
                        "backend_options": ({"device": args.device} if backend in ("dem", "ann") else {})
                        | ({"model": str(model)} if model is not None else {}),
                        "contact_law": asdict(law), "radius": radius,
                        "alpha0_deg": None if math.isnan(case_alpha0) else case_alpha0, "p0": p0,
                        "eps_max": args.eps_max, "increment": args.increment, "iso_increment": args.iso_increment,
                        "n_orientations": args.orientations, "fabric_anisotropy": 0.0, "fabric_direction_deg": 0.0,
                        "drained": args.drained, "stress_rtol": args.stress_rtol,
                        "mesostructure": source.text, "mesostructure_name": meso.name,
                        "mesostructure_file": source.text if source.kind is None else None,
                        "n_grains": meso.n_grains, "erode_at": erode_at,
                        "eroded_grains": ([int(g) + 1 for g in np.flatnonzero(~meso.driven.any(axis=1))]
                                          if erode_at is not None else None),
                    }
                    name = f"{source.label}__a{case_alpha0:g}__p{p0:g}__{backend}"
                    options = {"threads": args.threads} if backend == "dem" else {}
                    cases.append(Case(source.text, backend, case_alpha0, p0, _slug(name), parameters, options))
    if not cases:
        raise UserError("no case to run: " + "; ".join(skipped))
    _unique_folders(cases)
    return cases, skipped


def _closed_form_cell(meso: Mesostructure) -> tuple[float, float] | None:
    """(alpha0 [deg], grain radius [m]) of a cell the analytical backend models, else None."""
    if mesostructure_refusal("analytical", meso) is not None:
        return None
    return backend_class("analytical").check_mesostructure(meso), float(meso.radius[0])


def _unique_folders(cases: list[Case]) -> None:
    """Give cases that share a folder name a hash of their parameters (in place)."""
    seen: dict[str, int] = {}
    for case in cases:
        seen[case.folder] = seen.get(case.folder, 0) + 1
    for k, case in enumerate(cases):
        if seen[case.folder] > 1:
            digest = hashlib.sha1(json.dumps(case.parameters, sort_keys=True).encode()).hexdigest()[:8]
            cases[k] = dataclasses.replace(case, folder=f"{case.folder}__{digest}")


# -- one case ------------------------------------------------------------------------------------

class _ContinuedCell:
    """A cell model that starts from a given state and scales V_cell so that V0 is a given volume.

    The driver computes V0 from the areas of the initial state and J from the increments it
    applies; a test continued after erosion keeps the V0 J of the first part this way (the
    Love-Weber moments are untouched; observables report the true areas).
    """

    def __init__(self, inner: Any, state: Any, area_scale: float) -> None:
        self.inner = inner
        self.state = state
        self.area_scale = float(area_scale)
        self.name = inner.name

    def init_state(self, mesostructure: Mesostructure, n_cells: int) -> Any:
        if n_cells != self.state.n_cells:
            raise ValueError(f"continued state has {self.state.n_cells} cells, asked for {n_cells}")
        return self.state

    def response(self, state: Any):
        response = self.inner.response(state)
        return dataclasses.replace(response, area=response.area * self.area_scale)

    def step(self, state: Any, d_eps_local: np.ndarray, *, with_tangent: bool = False):
        new, response = self.inner.step(state, d_eps_local, with_tangent=with_tangent)
        return new, dataclasses.replace(response, area=response.area * self.area_scale)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def _join(first: driver.Record, second: driver.Record, programme: loading.Programme) -> driver.Record:
    """One record of a test run in two parts (``second`` continues ``first``)."""
    def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a, b])

    def cat_dict(a: dict, b: dict, n_a: int, n_b: int) -> dict:
        out = {}
        for name in dict.fromkeys([*a, *b]):
            va = a[name] if name in a else np.full((n_a, *np.shape(b[name])[1:]), np.nan)
            vb = b[name] if name in b else np.full((n_b, *np.shape(a[name])[1:]), np.nan)
            out[name] = np.concatenate([np.asarray(va, dtype=np.result_type(va, np.float64)),
                                        np.asarray(vb, dtype=np.result_type(vb, np.float64))])
        return out

    J1 = first.J[-1]
    eps11 = cat(first.eps11, second.eps11 + first.eps11[-1])
    eps22 = cat(first.eps22, second.eps22 + first.eps22[-1])
    J = cat(first.J, second.J * J1)
    return driver.Record(
        stage=cat(first.stage, second.stage), eps11=eps11, eps22=eps22,
        sigma11=cat(first.sigma11, second.sigma11), sigma22=cat(first.sigma22, second.sigma22),
        sigma12=cat(first.sigma12, second.sigma12), p=cat(first.p, second.p), q=cat(first.q, second.q),
        J=J, volume=first.V0 * J, newton_iterations=cat(first.newton_iterations, second.newton_iterations),
        diagnostics=cat_dict(first.diagnostics, second.diagnostics, first.n_increments, second.n_increments),
        snapshot_increment=cat(first.snapshot_increment, second.snapshot_increment + first.n_increments),
        snapshot_stage=cat(first.snapshot_stage, second.snapshot_stage),
        snapshots=cat_dict(first.snapshots, second.snapshots, first.snapshot_increment.size,
                           second.snapshot_increment.size),
        theta_deg=first.theta_deg, weights=first.weights, V0=first.V0, parameters=first.parameters,
        backend=first.backend, programme=programme, final_state=second.final_state,
        step_seconds=cat(first.step_seconds, second.step_seconds))


def run_test(cell_model: Any, case: Case, meso: Mesostructure) -> driver.Record:
    """The biaxial test of ``case`` on ``cell_model`` from cells of ``meso``, with erosion where the case asks for it."""
    prm = case.parameters
    common = dict(mesostructure=meso, n_orientations=prm["n_orientations"], stress_rtol=prm["stress_rtol"],
                  progress=False)
    full = loading.biaxial(case.p0, prm["eps_max"], prm["increment"], iso_increment=prm["iso_increment"],
                           drained=prm["drained"])
    if prm["erode_at"] is None:
        return driver.run(cell_model, full, **common)
    from warp_hcell.dem.erosion import erode_state

    iso, shear = full
    n_before = min(loading.n_increments_for(prm["erode_at"], prm["increment"]), shear.n_increments - 1)
    eps_before = prm["eps_max"] * n_before / shear.n_increments

    def shear_step(eps: float, n: int, label: str) -> loading.Step:
        if prm["drained"]:
            return loading.drained_biaxial(case.p0, eps, n, label=label)
        return loading.constant_volume_biaxial(eps, n, label=label)

    before = (iso, shear_step(eps_before, n_before, shear.label))
    relax = (loading.drained_biaxial(case.p0, 0.0, 1, label=ERODE_STAGE) if prm["drained"]
             else loading.proportional_strain(0.0, 0.0, 1, label=ERODE_STAGE))
    after = (relax,
             shear_step(prm["eps_max"] - eps_before, shear.n_increments - n_before, ERODED_STAGE))
    first = driver.run(cell_model, before, **common)
    state = cell_model.state_from_arrays(first.final_state)
    reduced, reduced_state, _ = erode_state(cell_model, state, [g - 1 for g in prm["eroded_grains"]])
    volume_now = float(first.weights @ reduced.response(reduced_state).area)
    continued = _ContinuedCell(reduced, reduced_state, first.V0 * first.J[-1] / volume_now)
    second = driver.run(continued, after, **common)
    return _join(first, second, before + after)


def summarise(record: driver.Record, p0: float) -> dict[str, float]:
    """Summary numbers of the shear stages of ``record`` (see the module docstring)."""
    curve = figures.shear_curve(record)
    eps1, p, q = curve.eps1[1:], curve.p[1:], curve.q[1:]
    peak = int(np.argmax(q))
    row = {"peak_q": q[peak], "eps1_at_peak": eps1[peak], "p_at_peak": p[peak],
           "p_end": p[-1], "q_end": q[-1], "eps1_end": eps1[-1]}
    for mark in STRAIN_MARKS:
        row[f"p_at_{round(100 * mark)}pct"] = float(np.interp(mark, eps1, p)) if eps1[-1] >= mark - 1e-12 else math.nan
    running = np.maximum.accumulate(q)
    fallen = np.flatnonzero(q < running - SOFTENING_DROP * p0)
    if fallen.size:
        first = int(np.argmax(q[: fallen[0] + 1]))
        row.update(first_peak_q=q[first], eps1_at_first_peak=eps1[first], p_at_first_peak=p[first])
    else:
        row.update(first_peak_q=math.nan, eps1_at_first_peak=math.nan, p_at_first_peak=math.nan)
    unconverged = record.diagnostics.get("n_unconverged")
    row["n_unconverged"] = float(np.nansum(unconverged)) if unconverged is not None else 0.0
    return {k: float(v) for k, v in row.items()}


def _summary_row(case: Case, record: driver.Record) -> dict[str, Any]:
    prm = case.parameters
    return {"mesostructure": case.source, "backend": case.backend, "alpha0": case.alpha0, "p0": case.p0,
            **summarise(record, case.p0), "erode_at": prm["erode_at"] if prm["erode_at"] is not None else math.nan,
            "n_grains": prm["n_grains"], "case": case.folder}


def compute_case(case: Case) -> driver.Record:
    """The record of one case (no file written): the task a worker runs."""
    prm = case.parameters
    options: dict[str, Any] = dict(prm["backend_options"]) | case.options
    meso = parse_mesostructure(case.source).build(None if math.isnan(case.alpha0) else case.alpha0)
    if "model" in options:
        options["model"] = Path(options["model"])
    model = make_cell_model(case.backend, contact_law=ContactLaw(**prm["contact_law"]), radius=prm["radius"], **options)
    return run_test(model, case, meso)


CASE_ERRORS = (driver.ControlError, ValueError, UserError, RuntimeError)
"""Exceptions that fail one case (listed at the end) instead of the sweep."""


def case_task(_shared: Any, case: Case) -> tuple[driver.Record | None, float, str | None]:
    """``warp_hcell.core.execution`` task: (record, wall seconds, None), or (None, seconds, error line)."""
    start = time.perf_counter()
    try:
        record = compute_case(case)
    except CASE_ERRORS as exc:
        return None, time.perf_counter() - start, " ".join(str(exc).split()) or type(exc).__name__
    return record, time.perf_counter() - start, None


def write_case(case: Case, record: driver.Record, out: Path, seed: int) -> dict[str, Any]:
    """Write the folder of a computed case (run.h5, curve.csv, figure); returns its summary row."""
    prm = case.parameters
    folder = Path(out) / CASES_DIR / case.folder
    io.write_run(folder, record, parameters=prm, seed=seed)
    figures.save_figure(figures.overlay_figure([figures.Run(record, prm)]), folder / FIGURE_FILE)
    return _summary_row(case, record)


def stored_row(case: Case, out: Path, *, overwrite: bool) -> dict[str, Any] | None:
    """Summary row of a finished case (same parameters on disk), None if it must run.

    Raises:
        UserError: the folder holds a run with other parameters and not ``overwrite``.
    """
    folder = out / CASES_DIR / case.folder
    run_file, curve_file = folder / io.RUN_FILE, folder / io.CURVE_FILE
    if not (run_file.is_file() and curve_file.is_file()):
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
    """Run ``cases`` on ``execution`` (``warp_hcell.core.execution``); write each case as it comes back.

    Returns:
        (rows, failures): summary rows and error messages, keyed by case folder.
    """
    rows: dict[str, dict] = {}
    failures: dict[str, str] = {}
    for case, (record, seconds, error) in execution.map(case_task, None, cases):
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
    text_columns = {"mesostructure", "backend", "case"}
    return [{k: (v if k in text_columns else float(v)) for k, v in row.items()} for row in rows]


def summary_figure(path: Path, cases: Sequence[Case], out: Path) -> Path:
    """Write summary.png (``make_summary_figure``) of ``cases`` stored under ``out``; returns ``path``."""
    runs = [figures.Run(io.read_run(out / CASES_DIR / case.folder / io.RUN_FILE).record, case.parameters)
            for case in cases]
    return figures.save_figure(make_summary_figure(runs), path)


def make_summary_figure(runs: Sequence[figures.Run]) -> Figure:
    """q/p0 and p/p0 against eps1 and the (p/p0, q/p0) path of every run; title and legend from their metadata."""
    fig = Figure(figsize=(15.0, 5.6), layout="constrained")
    ax_q, ax_p, ax_pq = fig.subplots(1, 3)
    title, labels = run_labels.split_labels([figures.describe_run(run) for run in runs])
    handles = []
    for colour, run, label in zip(plotting_colours(len(runs)), runs, labels):
        c = figures.shear_curve(run.record)
        p0 = figures.reference_pressure(run)
        style = {"color": colour, "lw": 1.0}
        (line,) = ax_q.plot(100.0 * c.eps1, c.q / p0, label=label or "_nolegend_", **style)
        ax_p.plot(100.0 * c.eps1, c.p / p0, **style)
        ax_pq.plot(c.p / p0, c.q / p0, **style)
        if label:
            handles.append(line)
    ax_q.set(xlabel=LABELS["eps1"], ylabel=LABELS["q/p0"], title="deviator")
    ax_p.set(xlabel=LABELS["eps1"], ylabel=LABELS["p/p0"], title="mean stress")
    ax_pq.set(xlabel=LABELS["p/p0"], ylabel=LABELS["q/p0"], title="stress path")
    for ax in (ax_q, ax_p, ax_pq):
        ax.grid(True, **GRID)
    if handles:
        figure_legend(fig, handles)
    fig.suptitle(f"sweep: {title} (compression positive)" if title else "sweep (compression positive)")
    return apply_style(fig)


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
    try:
        with atomic_write(out / SWEEP_FILE) as tmp:
            tmp.write_text(json.dumps(options, indent=1, sort_keys=True) + "\n")
    except OSError as exc:
        raise UserError(f"cannot write to {out}: {exc.strerror or exc}") from None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code (user errors are mapped to 2 by ``run_main``)."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    out: Path = args.out
    if args.device != "cpu" and not {"dem", "ann"} & set(args.backend):
        raise UserError("--device applies to --backend dem or ann only (analytical runs on the cpu)")
    cases, skipped = plan(args)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file; give a folder")
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
    options["mesostructure"] = [c.source for c in cases]
    _prepare_out(out, options, overwrite=args.overwrite)
    say(*(f"skipped: {note}" for note in skipped))
    say(f"{len(cases)} cases: {len(cases) - len(todo)} finished before, {len(todo)} to run")

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
