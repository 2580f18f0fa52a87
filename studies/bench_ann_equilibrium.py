"""python studies/bench_ann_equilibrium.py --model M.pt --mesostructure SPEC [--p0 2e5] [--test undrained] [--corrections 0,1,3] [--guesses network,still] [--escalation on,off] [--from-rest] [--part test|step]

The 3D meso-ANN alone against the ANN followed by K exact equilibrium corrections
(``AnnCell(equilibrium_corrections=K)``, docs/ann.md) and against the DEM, on one triaxial test of
one cell, all on the same rule of cells, printed side by side in one run:

- the largest difference from the DEM of sigma11, sigma22, sigma33, p and q along the shear stage,
  over p0 and over the path's scale max(p0, largest DEM p), and where it is (a run whose stress
  control fails is reported as stopped, with the driver's line), the same of q alone over the
  scale, the largest difference of the shear stage's volumetric strain eps11 + eps22 + eps33 (in % of strain), and the increments whose
  stress control accepted the nearer side of a response jump (``stress_control_jump``);
- the corrections' counts over the run: cell-increments corrected, Newton steps (and those the line
  search shortened or shifted), cell-increments left above the DEM's force tolerance (unconverged),
  the largest force ratio of the network's guess;
- the wall time of each run and its ratio to the DEM's (and to the closed form's, with
  ``--closed-form``, for the plain ten-sphere cell only), per increment.

``--part step``: one step call on the cells of ``--step-rule`` (default 53x16: 7792 cells) of the
DEM, the ANN alone and the ANN with each K (and the closed form with ``--closed-form``), each from its
own state after the same local increments (10 isotropic of 3e-4, then ``--step-shear`` undrained of
1e-4 along the cell axis: 300 catch the fine grain of ``hcell3d-fines:alpha0=55,ratio=0.9``), timed in turn ``--repeats`` times; the
medians and their ratios.

``--steps full`` adds rows whose corrections take full Newton steps (no shift, no line search, in the
compiled and the torch path), to measure what the globalisation adds.

``--escalation on,off`` adds rows of the hybrid that keeps the corrections' result where a free grain moved
and ends touching nothing (the package takes those cells' increment again with that grain starting the
corrections at rest, ``homogenization.ann.escalation``, ``AnnCell``; the column "to DEM" counts the cells
the DEM computes: those of ``sliding`` rows, or of another device than the CPU), ``sliding`` rows of a hybrid that also hands the DEM the cells where a grain
free along every axis slides (``DemEscalation(sliding=True)``, not the package's default); ``--from-rest`` adds the DEM started from rest in every increment (the map
the database samples), the DEM's own reproducibility. Beside the largest difference, the column "+-W inc."
is the largest difference of p and q when each increment may be matched with one of the other curve's within
``--window`` W increments (a drop at another increment costs nothing there); with ``--from-rest`` each
ANN row also says how far it is from the DEM started from rest (pointwise, over the DEM's scale).

``--guesses`` adds rows whose corrections start from another first guess than the network's
(``training.inference.FastAdvance``'s ``guess``: ``still``, the free grains do not move; ``affine``,
they follow the cell's strain), to measure what the network adds to the Newton steps (the network
is still evaluated, so the cost is the same). These rows need a strain-controlled shear stage
(``--test undrained``): stress control takes its tangent from the torch path, which starts from the
network. Strains [-], stresses [Pa], compression positive. Rows are also written as JSON lines
(``--json``).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
import sys
import warnings
from pathlib import Path

import numpy as np

from warp_hcell.core.cli import Parser, positive_float, positive_int

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_finegrain_hybrid as finegrain  # noqa: E402

COMPARED = ("sigma11", "sigma22", "sigma33", "p", "q")


def run(model, meso, args):
    """(record, wall time [s]) of the test on ``model``'s cells (the fine-grain benchmark's runner)."""
    return finegrain.run(model, meso, args, args.eps_max, args.test)


def difference(record, reference, p0: float, curves=COMPARED) -> tuple[float, float, float, str]:
    """(largest difference of the shear-stage curves [Pa], the path's scale [Pa], axial strain of the
    shear stage where it is [-], the curve) of ``record`` against ``reference``, increment by increment
    from the start of each one's shear stage (the isotropic stage lands on p0 in as many increments
    as each backend needs)."""
    def shear_stage(r):
        rows = np.flatnonzero(r.stage == r.stage[-1])
        return rows, float(r.eps11[rows[0] - 1]) if rows[0] > 0 else 0.0

    mine, _ = shear_stage(record)
    theirs, start = shear_stage(reference)
    n = min(mine.size, theirs.size)
    worst, where, name = 0.0, 0.0, ""
    for curve in curves:
        diff = np.abs(getattr(record, curve)[mine[:n]] - getattr(reference, curve)[theirs[:n]])
        k = int(np.argmax(diff))
        if diff[k] > worst:
            worst, where, name = float(diff[k]), float(reference.eps11[theirs[k]]) - start, curve
    return worst, max(p0, float(np.abs(reference.p).max())), where, name


def windowed_difference(record, reference, p0: float, window: int) -> float:
    """Largest difference of p and q over the path's scale [-] when each increment of one curve may be matched
    with any of the other's within ``window`` increments (both ways): a drop at another increment costs
    nothing, a curve off the other for longer than the window costs what it is off. ``window`` 0:
    ``difference`` of p and q."""
    def shear_stage(r):
        return np.flatnonzero(r.stage == r.stage[-1])

    mine, theirs = shear_stage(record), shear_stage(reference)
    n = min(mine.size, theirs.size)
    worst = 0.0
    for curve in ("p", "q"):
        a, b = getattr(record, curve)[mine[:n]], getattr(reference, curve)[theirs[:n]]
        for x, y in ((a, b), (b, a)):
            nearest = np.full(n, np.inf)
            for shift in range(-window, window + 1):
                lo, hi = max(0, -shift), min(n, n - shift)
                nearest[lo:hi] = np.minimum(nearest[lo:hi], np.abs(x[lo:hi] - y[lo + shift:hi + shift]))
            worst = max(worst, float(nearest.max()))
    return worst / max(p0, float(np.abs(reference.p).max()))


def volumetric_difference(record, reference) -> float:
    """Largest difference [-] of the shear stage's volumetric strain eps11 + eps22 + eps33 (from the stage's
    start, compression positive) against ``reference``, increment by increment as in ``difference``."""
    def shear_eps_v(r):
        rows = np.flatnonzero(r.stage == r.stage[-1])
        eps_v = r.eps11 + r.eps22 + r.eps33
        return eps_v[rows] - (eps_v[rows[0] - 1] if rows[0] > 0 else 0.0)

    mine, theirs = shear_eps_v(record), shear_eps_v(reference)
    n = min(mine.size, theirs.size)
    return float(np.abs(mine[:n] - theirs[:n]).max())


def total(record, key: str) -> float:
    values = record.diagnostics.get(key)
    return float(np.nansum(values)) if values is not None else float("nan")


def largest(record, key: str) -> float:
    values = record.diagnostics.get(key)
    return float(np.nanmax(values)) if values is not None else float("nan")


def step_part(args, meso, corrections, tolerances) -> None:
    """Median time of one step call per backend on the cells of ``--step-rule``, side by side."""
    from homogenization.backends import make_cell_model
    from homogenization.ann.cell import AnnCell3D
    from homogenization.material.orientation import orientations_3d
    from warp_hcell.core.parameters import ContactLaw

    order, spins = (int(v) for v in args.step_rule.split("x"))
    n = orientations_3d(order, spins).weights.size
    models = {"dem": make_cell_model("dem", dim=3, threads=1)}
    if args.closed_form:
        models["closed form"] = make_cell_model("analytical", dim=3)
    for k in corrections:
        for tol in tolerances if k else tolerances[:1]:
            name = "network alone" if not k else f"network + {k}" + (f" @{tol:g}" if len(tolerances) > 1 else "")
            models[name] = AnnCell3D(ContactLaw(), 0.5, model=args.model, equilibrium_corrections=k,
                                     equilibrium_tolerance=tol if k else None)
    iso, shear = np.full((n, 3), 3e-4), np.tile([1e-4, -5e-5, -5e-5], (n, 1))
    states, counts = {}, {}
    for name, model in models.items():
        state = model.init_state(meso, n)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for k in range(10 + args.step_shear):
                state, response = model.step(state, iso if k < 10 else shear)
        states[name] = state
        counts[name] = {key: response.diagnostics.get(key) for key in ("n_corrected", "n_corrections", "n_shortened",
                                                                       "n_shifted", "n_unconverged")}
    times = {name: [] for name in models}
    for _ in range(args.repeats):
        for name, model in models.items():
            start = time.perf_counter()
            model.step(states[name], shear)
            times[name].append(time.perf_counter() - start)
    ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    base = ms.get("closed form", ms["dem"])
    print(f"one step call, {n} cells ({args.step_rule}), median of {args.repeats}; load {os.getloadavg()[0]:.1f}")
    print(f"{'backend':>22} {'ms':>8} {'/ DEM':>6} {'/ closed':>8}  last increment's counts")
    for name in models:
        print(f"{name:>22} {ms[name]:8.1f} {ms[name] / ms['dem']:6.2f} "
              f"{ms[name] / base if 'closed form' in ms else float('nan'):8.2f}  "
              f"{ {k: v for k, v in counts[name].items() if v is not None} }")
    if args.json:
        with open(args.json, "a", encoding="utf-8") as out:
            out.write(json.dumps({"part": "step", "mesostructure": args.mesostructure, "model": args.model,
                                  "rule": args.step_rule, "cells": n, "repeats": args.repeats, "ms": ms,
                                  "load_average": os.getloadavg()[0]}) + "\n")


def main(argv=None) -> int:
    parser = Parser(description=__doc__.split("\n\n")[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a 3D meso-ANN model (.pt)")
    parser.add_argument("--mesostructure", required=True, help="the cell (a builder spec or a file)")
    parser.add_argument("--p0", type=positive_float, default=2e5, help="isotropic pressure [Pa]")
    parser.add_argument("--test", choices=("undrained", "drained"), default="undrained")
    parser.add_argument("--eps-max", type=positive_float, default=0.15, help="axial strain of the shear stage [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="shear increment [-]")
    parser.add_argument("--order", type=positive_int, default=11, help="Lebedev order of the cell axes")
    parser.add_argument("--spins", type=positive_int, default=4, help="spins per axis")
    parser.add_argument("--corrections", default="0,1,3", help="comma-separated K (0: the network alone)")
    parser.add_argument("--tolerances", default="1e-6", help="comma-separated force ratios above which a cell is "
                        "corrected (1e-6: the DEM's)")
    parser.add_argument("--steps", default="globalised", help="comma-separated Newton steps of the corrections: "
                        "globalised (the package's: shifted where they climb, halved by the line search) or full "
                        "(plain Newton steps, halvings 0 and shift 0 in both paths)")
    parser.add_argument("--escalation", default="on", help="comma-separated on/off/sliding: the hybrid hands the cells "
                        "with a released grain to the DEM (homogenization.ann.escalation) or not, or also "
                        "those where a free grain slides (DemEscalation(sliding=True), not the package's)")
    parser.add_argument("--from-rest", action="store_true", help="also the DEM started from rest in every increment "
                        "(the map the database samples): the DEM's own reproducibility")
    parser.add_argument("--window", type=positive_int, default=20, help="increments of the windowed difference")
    parser.add_argument("--guesses", default="network", help="comma-separated first guesses (network, still, affine)")
    parser.add_argument("--closed-form", action="store_true", help="also time the closed form (plain ten-sphere cell)")
    parser.add_argument("--part", choices=("test", "step"), default="test")
    parser.add_argument("--step-rule", default="53x16", help="step part: ORDERxSPINS of the cells")
    parser.add_argument("--repeats", type=positive_int, default=20, help="step part: timed calls per backend")
    parser.add_argument("--step-shear", type=positive_int, default=100,
                        help="step part: undrained increments of 1e-4 before the timed call")
    parser.add_argument("--json", default=None, help="append the rows as JSON lines to this file")
    args = parser.parse_args(argv)
    corrections = [int(k) for k in args.corrections.split(",")]
    tolerances = [float(t) for t in args.tolerances.split(",")]
    guesses = args.guesses.split(",")
    rules = args.steps.split(",")
    escalations = args.escalation.split(",")
    if any(e not in ("on", "off", "sliding") for e in escalations):
        parser.error(f"--escalation {args.escalation}: on, off and/or sliding")
    if any(rule not in ("globalised", "full") for rule in rules):
        parser.error(f"--steps {args.steps}: globalised and/or full")
    if any(g != "network" for g in guesses) and args.test != "undrained":
        parser.error("--guesses other than network need --test undrained (stress control starts from the network)")

    from homogenization.backends import make_cell_model
    from homogenization.ann import cell as ann_backend
    from homogenization.ann.cell import AnnCell3D
    from homogenization.ann.escalation import DemEscalation
    from homogenization.element_test.driver import ControlError
    from training.equilibrium import corrected_advance
    from training.inference import FastAdvance
    from warp_hcell.core.parameters import ContactLaw
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(args.mesostructure).build(None)
    if args.part == "step":
        step_part(args, meso, corrections, tolerances)
        return 0
    print(f"{args.mesostructure}, {args.test}, p0 = {args.p0:g} Pa, to {args.eps_max:g} at {args.increment:g}, rule "
          f"{args.order} x {args.spins}; load {os.getloadavg()[0]:.1f}")
    dem, dem_s = run(make_cell_model("dem", dim=3, threads=1), meso, args)
    rows = [{"variant": "dem", "wall_s": dem_s, "increments": dem.n_increments}]
    rest = None
    if args.from_rest:
        from homogenization.learning.from_rest import FromRest

        try:
            rest, rest_s = run(FromRest(make_cell_model("dem", dim=3, threads=1)), meso, args)
        except ControlError as exc:
            rows.append({"variant": "dem from rest", "stopped": str(exc)})
            print(f"dem from rest: stopped: {exc}")
        else:
            worst, scale, where, curve = difference(rest, dem, args.p0)
            rows.append({"variant": "dem from rest", "wall_s": rest_s, "diff_p0": worst / args.p0,
                         "diff_scale": worst / scale, "at_eps_a": where, "curve": curve,
                         "windowed": windowed_difference(rest, dem, args.p0, args.window)})
    if args.closed_form:
        closed, closed_s = run(make_cell_model("analytical", dim=3), meso, args)
        worst, scale, _, _ = difference(closed, dem, args.p0)
        rows.append({"variant": "closed form", "wall_s": closed_s, "diff_p0": worst / args.p0, "diff_scale": worst / scale})
    variants = [(guess, k, tol, rule, esc) for esc in escalations for rule in rules for guess in guesses
                for k in corrections for tol in (tolerances if k else tolerances[:1])
                if (guess == "network" or k) and (k or (rule == rules[0] and esc == escalations[0]))]
    for guess, k, tol, rule, esc in variants:
        name = ("network alone" if not k else f"{guess} + {k}" + (f" @{tol:g}" if len(tolerances) > 1 else "")
                + (f" {rule}" if len(rules) > 1 else "") + (" no DEM" if esc == "off" and len(escalations) > 1 else "")
                + (" sliding to DEM" if esc == "sliding" else ""))
        ann = AnnCell3D(ContactLaw(), 0.5, model=args.model, equilibrium_corrections=k,
                        equilibrium_tolerance=tol if k else None, dem_escalation=esc != "off")
        if k and esc == "sliding":
            ann.escalation = DemEscalation(ann.trained_on, ContactLaw(), float(ann.metadata["contact_tolerance"]),
                                           force_ratio=ann.force_tolerance, sliding=True)
        plain = {"halvings": 0, "shift": 0.0} if rule == "full" else {}
        if guess != "network" or plain:
            ann.fast = FastAdvance(ann.net, k, ann.force_tolerance, guess, **plain)
        ann_backend.corrected_advance = functools.partial(corrected_advance, **plain)
        try:
            record, wall = run(ann, meso, args)
        except ControlError as exc:
            rows.append({"variant": name, "guess": guess, "corrections": k, "tolerance": tol, "steps": rule,
                         "escalation": esc, "stopped": str(exc)})
            print(f"{rows[-1]['variant']}: stopped: {exc}")
            continue
        worst, scale, where, curve = difference(record, dem, args.p0)
        rows.append({"variant": name, "guess": guess, "corrections": k, "tolerance": tol if k else None, "steps": rule,
                     "escalation": esc, "windowed": windowed_difference(record, dem, args.p0, args.window),
                     **({"diff_from_rest": difference(record, rest, args.p0)[0] / scale} if rest is not None else {}),
                     "escalated": total(record, "n_escalated"), "wall_s": wall, "diff_p0": worst / args.p0, "diff_scale": worst / scale, "scale_pa": scale,
                     "at_eps_a": where, "curve": curve, "increments": record.n_increments,
                     "q_diff_scale": difference(record, dem, args.p0, ("q",))[0] / scale,
                     "eps_v_diff": volumetric_difference(record, dem), "jumps": total(record, "stress_control_jump"),
                     "corrected": total(record, "n_corrected"), "newton_steps": total(record, "n_corrections"),
                     "shortened": total(record, "n_shortened"), "shifted": total(record, "n_shifted"),
                     "unconverged": total(record, "n_unconverged"),
                     "network_ratio_max": largest(record, "force_ratio_network_max"),
                     "ratio_max": largest(record, "force_ratio_max"),
                     "cell_increments": record.n_increments * int(np.asarray(record.weights).size)})
    print(f"{'variant':>22} {'diff/p0':>9} {'diff/scale':>10} {f'+-{args.window} inc.':>10} {'at eps_a':>8} "
          f"{'corrected':>10} {'Newton':>10} {'shortened':>9} {'shifted':>8} {'to DEM':>8} "
          f"{'unconv.':>8} {'guess ratio':>11} {'q/scale':>8} {'eps_v diff':>10} {'jumps':>5} {'wall s':>7} {'/ DEM':>6}" + (f" {'/ closed':>8}" if args.closed_form else ""))
    closed_s = next((r["wall_s"] for r in rows if r["variant"] == "closed form"), None)
    for row in rows:
        if "stopped" in row:
            print(f"{row['variant']:>22} stopped (stress control; line above)")
            continue
        cells = (f"{100 * row['diff_p0']:8.3g}% {100 * row['diff_scale']:9.3g}%" if "diff_p0" in row else f"{'':>9} {'':>10}")
        cells += f" {100 * row['windowed']:9.3g}%" if "windowed" in row else f" {'':>10}"
        extra = (f" {row['at_eps_a']:8.4f} {row['corrected']:10.0f} {row['newton_steps']:10.0f} "
                 f"{row['shortened']:9.0f} {row['shifted']:8.0f} {row['escalated']:8.0f} "
                 f"{row['unconverged']:8.0f} "
                 f"{row['network_ratio_max']:11.2g} {100 * row['q_diff_scale']:7.3g}% {100 * row['eps_v_diff']:9.3g}% "
                 f"{row['jumps']:5.0f}" if "corrected" in row
                 else f" {'':>8} {'':>10} {'':>10} {'':>9} {'':>8} {'':>8} {'':>8} {'':>11} {'':>8} {'':>10} {'':>5}")
        print(f"{row['variant']:>22} {cells}{extra} {row['wall_s']:7.1f} {row['wall_s'] / dem_s:6.2f}"
              + (f" {row['wall_s'] / closed_s:8.2f}" if closed_s else "")
              + (f"  off the DEM from rest by {100 * row['diff_from_rest']:.3g}%" if "diff_from_rest" in row else ""))
    if args.json:
        with open(args.json, "a", encoding="utf-8") as out:
            for row in rows:
                out.write(json.dumps({"mesostructure": args.mesostructure, "model": args.model, "p0": args.p0,
                                      "test": args.test, "increment": args.increment, "eps_max": args.eps_max,
                                      "rule": f"{args.order}x{args.spins}", **row}) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
