"""python benchmarks/bench_finegrain_hybrid.py (--models DIR [--cells NAME ...] | --model M.pt [--mesostructure CELL]) [--order 53 --spins 16] [--tests undrained drained] [--repeats 1]: the certified hybrid of 3D cells with a fine grain against the DEM.

With ``--models DIR``, every fine-grain cell of ``benchmarks/cells/`` (or those ``--cells`` names, file stems)
with the model ``DIR/<stem>/ann.pt`` (each built by the cell's default pipeline, ``hmodel generate`` then
``hmodel train``); with ``--model``, one cell. For each cell and test (triaxial compression at ``--p0`` to
``--eps-max`` at ``--increment``, isotropic stage at half the increment, the cells of Lebedev order
``--order`` with ``--spins`` spins: 53 x 16 = 7792 cells, ``hmodel triaxial``'s default) the DEM (one
thread) and the ANN model's hybrid (the certificate's K, R and released-grain rule, as ``hmodel triaxial
--backend ann --model M.pt`` runs it) run in one process, interleaved (DEM, ANN, DEM, ANN, ... ``--repeats``
times each), after a short run of each test and backend that compiles their kernels. Prints per run its wall time, and per
test the ratio ANN / DEM of the medians beside the accuracy (largest difference of sigma11, sigma22,
sigma33, p and q over the shear stage, increment by increment, over the path's scale max(p0, largest DEM
p)) and the hybrid's counts: Newton corrections per increment (every step call, trial calls included),
cells corrected per increment, cell-increments with a released grain (taken again from rest; of them
those whose grain a neighbour pushed), those whose grains nothing pressed started at rest (the released-grain
rule of newer certificates, ``homogenization.ann.escalation.RELEASE_RULE``), those relaxed as the DEM from rest
(``RELEASE_RULE_DRAG``), escalated to the DEM, left unconverged, step calls with a tangent
and the cells of those calls that took no correction (their tangent is that of their balance, not the
network's), and the ANN's step wall time split into phases [s]. Beside each wall time, the process's CPU
time, which other jobs on a shared machine move less, and its ratio. A table of all cells and tests ends the
output. The load average is printed before and after. JSON lines with ``--json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CELLS = ROOT / "benchmarks" / "cells"
FINE = CELLS / "fine_off_centre.toml"
COMPARED = ("sigma11", "sigma22", "sigma33", "p", "q")


def difference(record, reference, p0: float) -> tuple[float, float]:
    """(largest difference of the shear stage's ``COMPARED`` curves [Pa], the path's scale [Pa]), increment by
    increment from the start of each record's shear stage."""
    def shear(r):
        return np.flatnonzero(r.stage == r.stage[-1])

    mine, theirs = shear(record), shear(reference)
    n = min(mine.size, theirs.size)
    worst = max(float(np.abs(getattr(record, c)[mine[:n]] - getattr(reference, c)[theirs[:n]]).max()) for c in COMPARED)
    return worst, max(p0, float(np.abs(reference.p).max()))


def total(record, key: str) -> float:
    """Sum over the increments of a diagnostic (NaN where absent)."""
    values = record.diagnostics.get(key)
    return float(np.nansum(values)) if values is not None else float("nan")


class PhaseTimer:
    """Wall seconds spent in named callables of one ANN cell model (wrapped in place), each phase's own: the
    time of a wrapped callable inside another counts for the inner one only."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._inner: list[float] = []

    def wrap(self, owner, attribute: str, phase: str) -> None:
        inner = getattr(owner, attribute)

        @functools.wraps(inner)
        def timed(*args, **kwargs):
            self._inner.append(0.0)
            start = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                self.seconds[phase] += elapsed - self._inner.pop()
                if self._inner:
                    self._inner[-1] += elapsed

        setattr(owner, attribute, timed)

    def reset(self) -> None:
        self.seconds.clear()


def ann_model(path: str, timer: PhaseTimer | None, corrections: int | None = None, tolerance: float | None = None):
    """The hybrid of ``path`` as ``hmodel triaxial`` builds it (K and R: the certificate's, or those given), with its
    phases timed by ``timer``."""
    from homogenization.backends import make_cell_model

    model = make_cell_model("ann", dim=3, model=path, threads=1, equilibrium_corrections=corrections,
                            equilibrium_tolerance=tolerance)
    if timer is not None:
        fast = model.fast
        for attribute, phase in (("_features", "features"), ("_hold", "rest rule"), ("_newton", "corrections"),
                                 ("_physics", "contact law"), ("_advance", "contact law")):
            if getattr(fast, attribute, None) is not None:
                timer.wrap(fast, attribute, phase)
        if getattr(fast, "_forward", None) is not None:  # the perceptron's layers in one compiled call
            timer.wrap(fast, "_forward", "network")
        else:
            timer.wrap(fast.perceptron, "forward", "network")
        if model.escalation is not None:
            timer.wrap(model.escalation, "released_dofs", "release test")
            timer.wrap(model.escalation, "advance", "DEM escalation")
            timer.wrap(model, "_held_at_rest", "released again from rest")
            timer.wrap(model, "_dragged", "pushed grains relaxed")
        timer.wrap(model, "step", "step")
    return model


def run(model, meso, args, eps_max: float, test: str):
    """(record, wall seconds) of one triaxial test."""
    from homogenization.element_test import driver, programme as programmes

    programme = programmes.triaxial(args.p0, eps_max, args.increment, test=test, iso_increment=0.5 * args.increment)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        record = driver.run(model, programme, mesostructure=meso, lebedev_order=args.order, n_spins=args.spins,
                            progress=False)
    return record, time.perf_counter() - start


class TangentCount:
    """Step calls of one ANN cell model that asked for a tangent, and the cells of those calls that took no
    correction (``n_corrected`` of the call's diagnostics), counted by wrapping ``step`` in place."""

    def __init__(self, model) -> None:
        self.calls, self.uncorrected = 0, 0
        inner = model.step

        @functools.wraps(inner)
        def counted(state, d_eps_local, *, with_tangent=False):
            new, response = inner(state, d_eps_local, with_tangent=with_tangent)
            if with_tangent:
                self.calls += 1
                n = len(d_eps_local)
                self.uncorrected += n - int(response.diagnostics.get("n_corrected", n))
            return new, response

        model.step = counted

    def reset(self) -> None:
        self.calls, self.uncorrected = 0, 0


def warm_relaxation(ann, meso) -> None:
    """Where the hybrid runs ``RELEASE_RULE_DRAG``: one relaxation (``DemEscalation.relaxed``) of one cell of ``meso`` at
    rest with no grain pushed, so that its compiled kernel is loaded or compiled; nothing moves."""
    from homogenization.ann.escalation import RELEASE_RULE_DRAG  # noqa: PLC0415

    if ann.escalation is None or getattr(ann, "release_rule", None) != RELEASE_RULE_DRAG:
        return
    x = np.ascontiguousarray(np.asarray(meso.position, dtype=np.float64)[None])
    pushed = np.zeros((1, int(np.count_nonzero(~np.asarray(meso.driven)))), dtype=bool)
    ann.escalation.relaxed(x, x, np.zeros((1, len(meso.pairs), 3)), np.zeros((1, 3)), pushed)


def add_cell_arguments(parser, *, one_cell: bool = False, order: int = 53, spins: int = 16) -> None:
    """The arguments that ``cells_of`` reads and a triaxial test's loading: --models/--cells (``one_cell``: one
    stem) or --model/--mesostructure, --p0 [Pa], --eps-max, --increment [-], --order and --spins (defaults
    ``order``, ``spins``)."""
    from warp_hcell.core.cli import positive_float, positive_int

    parser.add_argument("--models", default=None, help="folder with <cell stem>/ann.pt for the cells of benchmarks/cells")
    parser.add_argument("--cells", nargs=1 if one_cell else "+", default=None,
                        help="one stem of benchmarks/cells/*.toml" if one_cell
                        else "stems of benchmarks/cells/*.toml (default: all)")
    parser.add_argument("--model", default=None, help="a 3D meso-ANN model (.pt) of --mesostructure, certified as the hybrid")
    parser.add_argument("--mesostructure", default=str(FINE), help="the cell of --model (a file or a builder spec)")
    parser.add_argument("--p0", type=positive_float, default=2e5, help="isotropic pressure [Pa]")
    parser.add_argument("--eps-max", type=positive_float, default=0.05, help="axial strain of the shear stage [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--order", type=positive_int, default=order, help="Lebedev order of the cell axes")
    parser.add_argument("--spins", type=positive_int, default=spins, help="spins per axis")


def cells_of(args, parser) -> list[tuple[str, str]]:
    """(mesostructure, model path) of every cell to run; a missing model or cell is a usage error."""
    if (args.model is None) == (args.models is None):
        parser.error("give --models DIR (the cells of benchmarks/cells) or --model M.pt (one cell)")
    if args.model is not None:
        pairs = [(args.mesostructure, args.model)]
    else:
        names = args.cells or sorted(p.stem for p in CELLS.glob("*.toml"))
        pairs = [(str(CELLS / f"{name}.toml"), str(Path(args.models) / name / "ann.pt")) for name in names]
    for meso, model in pairs:
        if args.model is None and not Path(meso).is_file():
            parser.error(f"--cells: no {meso}")
        if not Path(model).is_file():
            parser.error(f"no model {model}; build it: hmodel generate --mesostructure {meso} --seed 0 "
                         f"--out DIR/db.h5, then hmodel train --data DIR/db.h5 --out {model}")
    return pairs


def main(argv=None) -> int:
    from warp_hcell.core.cli import Parser, positive_float, positive_int

    parser = Parser(description=__doc__.split("\n\n")[0])
    add_cell_arguments(parser)
    parser.add_argument("--tests", nargs="+", choices=("undrained", "drained"), default=["undrained", "drained"])
    parser.add_argument("--repeats", type=positive_int, default=1, help="runs of each backend per test, interleaved")
    parser.add_argument("--equilibrium-corrections", type=int, default=None,
                        help="K of the hybrid (None: the certificate's; a model being certified: 20 for a fine grain)")
    parser.add_argument("--equilibrium-tolerance", type=positive_float, default=None, help="R of the hybrid (None: the certificate's)")
    parser.add_argument("--json", default=None, help="append one JSON line per cell and test to this file")
    args = parser.parse_args(argv)
    pairs = cells_of(args, parser)

    from homogenization.backends import make_cell_model
    from homogenization.material.orientation import orientations_3d
    from warp_hcell.mesostructures.builders import mesostructure_arg

    cells = orientations_3d(args.order, args.spins).weights.size
    rows = []
    dem = make_cell_model("dem", dim=3, threads=1)
    for mesostructure, model_path in pairs:
        meso = mesostructure_arg(mesostructure).build(None)
        timer = PhaseTimer()
        ann = ann_model(model_path, timer, args.equilibrium_corrections, args.equilibrium_tolerance)
        tangents = TangentCount(ann)
        print(f"{mesostructure}; model {model_path} (K = {ann.equilibrium_corrections}, R = {ann.force_tolerance:g}, "
              f"DEM escalation {'on' if ann.escalation is not None else 'off'}, released-grain rule "
              f"{getattr(ann, 'release_rule', None)!r}; {ann.certificate_problem or 'certified'}); "
              f"rule {args.order} x {args.spins}; load average {os.getloadavg()}", flush=True)
        compile_args = argparse.Namespace(**{**vars(args), "order": 3, "spins": 1})
        for model in (dem, ann):
            for test in args.tests:
                run(model, meso, compile_args, 10 * args.increment, test)
        warm_relaxation(ann, meso)  # the drag rule's kernel loads (or compiles) on first use: here, not in a timed run
        for test in args.tests:
            walls: dict[str, list[float]] = {"dem": [], "ann": []}
            cpus: dict[str, list[float]] = {"dem": [], "ann": []}
            records = {}
            phases: list[dict[str, float]] = []
            for _ in range(args.repeats):
                for name, model in (("dem", dem), ("ann", ann)):
                    timer.reset()
                    tangents.reset()
                    cpu = time.process_time()
                    records[name], wall = run(model, meso, args, args.eps_max, test)
                    walls[name].append(wall)
                    cpus[name].append(time.process_time() - cpu)
                    if name == "ann":
                        phases.append(dict(timer.seconds))
                    print(f"  {test} {name}: {wall:.1f} s, CPU {cpus[name][-1]:.1f} s ({records[name].n_increments} increments; load "
                          f"{os.getloadavg()[0]:.2f})", flush=True)
            worst, scale = difference(records["ann"], records["dem"], args.p0)
            dem_s, ann_s = statistics.median(walls["dem"]), statistics.median(walls["ann"])
            cpu_ratio = statistics.median(cpus["ann"]) / statistics.median(cpus["dem"])
            record = records["ann"]
            n = record.n_increments
            counts = {"corrections_per_increment": total(record, "n_corrections_all_calls") / n,
                      "corrected_per_increment": total(record, "n_corrected_all_calls") / n,
                      "released": total(record, "n_released_all_calls"),
                      "released_pushed": total(record, "n_released_pushed_all_calls"),
                      "resting": total(record, "n_resting_all_calls"),
                      "escalated": total(record, "n_escalated_all_calls"),
                      "relaxed": total(record, "n_relaxed_all_calls"),
                      "relaxed_substeps": total(record, "n_relaxed_substeps_all_calls"),
                      "relaxed_unconverged": total(record, "n_relaxed_unconverged_all_calls"),
                      "unconverged": total(record, "n_unconverged_all_calls"),
                      "step_calls": float(record.newton_iterations.sum()),
                      "tangent_calls": float(tangents.calls), "tangent_uncorrected": float(tangents.uncorrected)}
            phase = phases[-1]
            phase["outside step"] = walls["ann"][-1] - sum(phase.values())
            phase["rest of step"] = phase.pop("step", float("nan"))
            print(f"{test}: DEM {dem_s:.1f} s, ANN {ann_s:.1f} s, ANN / DEM = {ann_s / dem_s:.3f} (CPU time: "
                  f"{cpu_ratio:.3f}); max |diff| / scale = "
                  f"{worst / scale:.2e} (scale {scale:.3g} Pa); {cells} cells, "
                  f"{n} increments, {counts['step_calls']:.0f} step calls; Newton corrections per increment "
                  f"{counts['corrections_per_increment']:.0f}, cells corrected per increment "
                  f"{counts['corrected_per_increment']:.0f}; cell-increments started with a resting grain at rest "
                  f"{counts['resting']:.0f}, released {counts['released']:.0f} (taken again from rest unless their "
                  f"grain started there; of them pushed {counts['released_pushed']:.0f}), escalated to the DEM "
                  f"{counts['escalated']:.0f}, relaxed as the DEM from rest {counts['relaxed']:.0f} ("
                  f"{counts['relaxed_substeps']:.0f} substeps, {counts['relaxed_unconverged']:.0f} at the cap; "
                  f"RELEASE_RULE_DRAG only, NaN otherwise), unconverged {counts['unconverged']:.0f}; {tangents.calls} calls with a "
                  f"tangent, {tangents.uncorrected} of their cell steps uncorrected", flush=True)
            print("  ANN phases [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in phase.items()), flush=True)
            rows.append((Path(mesostructure).stem, test, dem_s, ann_s, worst / scale, {**counts, "cpu_ratio": cpu_ratio}))
            if args.json:
                with open(args.json, "a", encoding="utf-8") as out:
                    out.write(json.dumps({"test": test, "model": model_path, "mesostructure": mesostructure,
                                          "rule": [args.order, args.spins], "eps_max": args.eps_max,
                                          "dem_s": walls["dem"], "ann_s": walls["ann"], "ratio": ann_s / dem_s,
                                          "dem_cpu_s": cpus["dem"], "ann_cpu_s": cpus["ann"], "cpu_ratio": cpu_ratio,
                                          "diff_scale": worst / scale, **counts, "phases_s": phase,
                                          "load_average": os.getloadavg()}) + "\n")
    print(f"\n{cells} cells, to {args.eps_max:g} at {args.increment:g}; medians of {args.repeats} run(s) each")
    print(f"{'cell':<24}{'test':<11}{'DEM [s]':>9}{'ANN [s]':>9}{'ANN/DEM':>9}{'CPU':>7}{'diff/scale':>12}{'released':>10}"
          f"{'pushed':>9}{'to DEM':>8}{'unconv.':>9}{'tangents':>10}{'uncorr.':>9}")
    for name, test, dem_s, ann_s, diff, c in rows:
        print(f"{name:<24}{test:<11}{dem_s:>9.1f}{ann_s:>9.1f}{ann_s / dem_s:>9.3f}{c['cpu_ratio']:>7.3f}{diff:>12.2e}{c['released']:>10.0f}"
              f"{c['released_pushed']:>9.0f}{c['escalated']:>8.0f}{c['unconverged']:>9.0f}{c['tangent_calls']:>10.0f}"
              f"{c['tangent_uncorrected']:>9.0f}")
    print(f"load average after: {os.getloadavg()}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
