"""python benchmarks/bench_triaxial.py [--part accuracy,quadrature,timing,ann,ann3d-step] [--model M.pt] [--eps-max 0.15] [--increment 1e-4]

Acceptance of the 3D homogenisation (docs/triaxial.md), five parts, each printed as a table and
written as one JSON line per row:

- ``accuracy``: DEM vs the 3D closed form (``analytical``), undrained and drained triaxial
  compression, loose (alpha0 = 55 deg) and dense (``--dense``, 47 deg: equal spheres need
  alpha0 > 45 deg in 3D) cells, p0 = 2e5 and 5.85e6 Pa: the largest difference of sigma11,
  sigma22, sigma33, p and q along the path over p0 (target <= 1e-3), over the whole path and up to
  the first cross-plane contact (where the closed form stops holding: lateral grains of the two
  planes touch, ``n_cross_plane``; the axial strain of the shear stage there is printed), with the
  cell-increments that had such contacts and the unconverged DEM cell-increments;
- ``quadrature``: the closed form on each rule of ``--rules`` (ORDERxSPINS) against about twice
  the cells in each of the two ways (twice the spins; the first Lebedev order with at least twice
  the axes, ``doubled_axes_order``) and against the fine ``--reference`` rule: the largest
  difference of the curves over p0 (the target: doubling moves the curves by <= 0.5 % of p0) and
  over the path's scale max(p0, largest p of the reference);
- ``timing``: the wall time of the same triaxial test (loose, p0 = 2e5, undrained and drained) with
  the DEM and with the closed form, side by side, and their ratio (target <= 3);
- ``ann`` (only with ``--model``, a 3D meso-ANN): the model against the closed form, undrained
  triaxial compression of the loose cell at p0 = 2e5 and 5.85e6 Pa, the largest difference of the
  shear-stage curves over p0 (target <= 1 %) and over the path's scale max(p0, largest p), the
  isotropic strain at p0 of both, and the wall time of
  both runs side by side with the time per step call;
- ``ann3d-step``: one step call of the 3D meso-ANN (the shipped model, or ``--model``) against one of
  the closed form on the cells of the default rule (``--step-rule``, 53x16: 7792 cells), each from a
  state compressed isotropically to about p0 = 2e5 Pa and sheared to 1 % axial strain (undrained
  increments, not equilibrated: the same local increments for both), the two backends timed in turn
  ``--repeats`` times; the medians and their ratio (target <= 1), and the torch path's median.

Strains [-], stresses [Pa], compression positive. The machine load is printed with the timings.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
import warnings

import numpy as np

from homogenization.material.orientation import LEBEDEV_ORDERS
from warp_hcell.core.cli import Parser, positive_float, positive_int

PARTS = ("accuracy", "quadrature", "timing", "ann", "ann3d-step")
COMPARED = ("sigma11", "sigma22", "sigma33", "p", "q")


def run(backend: str, alpha0: float, p0: float, test: str, args, *, order: int | None = None,
        spins: int | None = None):
    """(record, wall time [s]) of one triaxial test; DEM and ANN warnings counted, not raised."""
    from homogenization.element_test import driver, programme as programmes
    from homogenization.backends import make_cell_model
    from warp_hcell.mesostructures.builders import mesostructure_arg

    meso = mesostructure_arg(f"hcell3d:alpha0={alpha0:g}").build(alpha0)
    programme = programmes.triaxial(p0, args.eps_max, args.increment, test=test, iso_increment=0.5 * args.increment)
    options = {"threads": args.threads} if backend == "dem" and args.threads else {}
    if backend == "ann":
        options["model"] = args.model
    model = make_cell_model(backend, dim=3, **options)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        record = driver.run(model, programme, mesostructure=meso, lebedev_order=order or args.order,
                            n_spins=spins or args.spins, progress=False)
    return record, time.perf_counter() - start


def largest_difference(a, b, n: int | None = None) -> float:
    """Largest difference of the compared curves [Pa] over the first ``n`` increments (None: all)."""
    n = min(a.n_increments, b.n_increments) if n is None else n
    if n == 0:
        return 0.0
    return max(float(np.abs(getattr(a, name)[:n] - getattr(b, name)[:n]).max()) for name in COMPARED)


def first_cross_plane(record) -> int:
    """Increments before the first with a cross-plane contact in the closed form (all if none)."""
    cross = record.diagnostics.get("n_cross_plane")
    hits = np.flatnonzero(np.nan_to_num(cross) > 0) if cross is not None else np.zeros(0, dtype=int)
    return int(hits[0]) if hits.size else record.n_increments


def shear_strain_at(record, k: int) -> float:
    """Axial strain [-] of the shear stage after increment ``k`` (NaN when k is past the end)."""
    start = int(np.flatnonzero(record.stage == record.stage[0])[-1])
    return float(record.eps11[k] - record.eps11[start]) if k < record.n_increments else float("nan")


def count(record, name: str) -> int:
    values = record.diagnostics.get(name)
    return 0 if values is None else int(np.nansum(values))


def accuracy(args) -> None:
    print(f"{'alpha0':>6} {'p0 [Pa]':>9} {'test':>9} {'max diff / p0':>14} {'before contact':>14} "
          f"{'first contact eps_a':>19} {'cross-plane':>11} {'unconverged':>11}")
    for alpha0 in (args.loose, args.dense):
        for p0 in (2e5, 5.85e6):
            for test in ("undrained", "drained"):
                closed, _ = run("analytical", alpha0, p0, test, args)
                dem, _ = run("dem", alpha0, p0, test, args)
                valid = first_cross_plane(closed)
                row = {"part": "accuracy", "alpha0_deg": alpha0, "p0": p0, "test": test,
                       "max_diff_over_p0": largest_difference(closed, dem) / p0,
                       "max_diff_before_contact_over_p0": largest_difference(closed, dem, valid) / p0,
                       "first_contact_shear_strain": (None if valid == closed.n_increments
                                                      else shear_strain_at(closed, valid)),
                       "n_increments": [closed.n_increments, dem.n_increments],
                       "cross_plane_cell_increments": count(closed, "n_cross_plane"),
                       "dem_unconverged": count(dem, "n_unconverged")}
                print(f"{alpha0:6g} {p0:9.3g} {test:>9} {row['max_diff_over_p0']:14.3g} "
                      f"{row['max_diff_before_contact_over_p0']:14.3g} {shear_strain_at(closed, valid):19.4g} "
                      f"{row['cross_plane_cell_increments']:11d} {row['dem_unconverged']:11d}", flush=True)
                print(json.dumps(row))


def rule(text: str) -> tuple[int, int]:
    """(order, spins) of a rule written ORDERxSPINS, e.g. ``23x8``."""
    order, _, spins = text.partition("x")
    return int(order), int(spins)


def doubled_axes_order(order: int) -> int:
    """The first Lebedev order with at least twice the hemisphere axes of ``order`` (``order`` itself
    at the end of the list)."""
    from homogenization.material.orientation import hemisphere_rule

    axes = hemisphere_rule(order)[0].shape[0]
    return next((o for o in LEBEDEV_ORDERS if o > order and hemisphere_rule(o)[0].shape[0] >= 2 * axes), order)


def quadrature(args) -> None:
    reference_rule = None if args.reference == "none" else rule(args.reference)
    rules = [rule(text) for text in args.rules.split(",")]
    print(f"{'alpha0':>6} {'p0 [Pa]':>9} {'test':>9} {'rule':>6} {'cells':>6} {'x2 spins / p0':>13} "
          f"{'x2 axes / p0':>12} {'vs reference / p0':>17} {'/ scale':>8} {'wall [s]':>8}")
    for alpha0 in (args.loose, args.dense):
        for p0 in (2e5, 5.85e6):
            for test in ("undrained", "drained"):
                reference = (None if reference_rule is None else
                             run("analytical", alpha0, p0, test, args, order=reference_rule[0], spins=reference_rule[1])[0])
                for order, spins in rules:
                    base, wall = run("analytical", alpha0, p0, test, args, order=order, spins=spins)
                    doubled, _ = run("analytical", alpha0, p0, test, args, order=order, spins=2 * spins)
                    finer = doubled_axes_order(order)
                    more_axes, _ = run("analytical", alpha0, p0, test, args, order=finer, spins=spins)
                    scale = max(p0, float((base if reference is None else reference).p.max()))
                    to_reference = math.nan if reference is None else largest_difference(base, reference)
                    row = {"part": "quadrature", "alpha0_deg": alpha0, "p0": p0, "test": test, "rule": [order, spins],
                           "cells": int(base.weights.size), "reference": None if reference is None else list(reference_rule),
                           "reference_cells": None if reference is None else int(reference.weights.size),
                           "doubled_spins_over_p0": largest_difference(base, doubled) / p0,
                           "doubled_axes_order": finer, "doubled_axes_cells": int(more_axes.weights.size),
                           "doubled_axes_over_p0": largest_difference(base, more_axes) / p0,
                           "to_reference_over_p0": to_reference / p0, "to_reference_over_scale": to_reference / scale,
                           "staggered": True, "wall_s": wall}
                    print(f"{alpha0:6g} {p0:9.3g} {test:>9} {order:>3}x{spins:<2} {row['cells']:6d} "
                          f"{row['doubled_spins_over_p0']:13.3g} {row['doubled_axes_over_p0']:12.3g} "
                          f"{row['to_reference_over_p0']:17.3g} {row['to_reference_over_scale']:8.3g} {wall:8.1f}",
                          flush=True)
                    print(json.dumps(row))


def timing(args) -> None:
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    run("dem", args.loose, 2e5, "undrained", args, order=3, spins=1)  # Warp start-up and kernel load, not timed
    print(f"{'test':>9} {'cells':>5} {'increments':>10} {'analytical [s]':>14} {'dem [s]':>9} {'dem / analytical':>16}")
    for test in ("undrained", "drained"):
        closed, t_closed = run("analytical", args.loose, 2e5, test, args)
        dem, t_dem = run("dem", args.loose, 2e5, test, args)
        row = {"part": "timing", "test": test, "cells": int(closed.weights.size), "n_increments": closed.n_increments,
               "analytical_s": t_closed, "dem_s": t_dem, "ratio": t_dem / t_closed,
               "step_calls": [int(closed.newton_iterations.sum()), int(dem.newton_iterations.sum())],
               "load_average": os.getloadavg()[0]}
        print(f"{test:>9} {row['cells']:5d} {row['n_increments']:10d} {t_closed:14.2f} {t_dem:9.2f} {row['ratio']:16.2f}",
              flush=True)
        print(json.dumps(row))


def shear_difference(a, b) -> float:
    """Largest difference of the compared curves [Pa] over the shear stages of two records, increment by
    increment from the end of the isotropic stage (whose increment count follows each backend's response)."""
    curves = []
    for record in (a, b):
        shear = record.stage != record.stage[0]
        curves.append({name: getattr(record, name)[shear] for name in COMPARED})
    n = min(curves[0]["p"].size, curves[1]["p"].size)
    return max(float(np.abs(curves[0][name][:n] - curves[1][name][:n]).max()) for name in COMPARED)


def ann(args) -> None:
    if args.model is None:
        print("no --model: part skipped")
        return
    print(f"model {args.model}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    print(f"{'p0 [Pa]':>9} {'test':>9} {'cells':>5} {'max diff / p0':>13} {'/ scale':>8} {'analytical [s]':>14} "
          f"{'ann [s]':>8} {'ann / analytical':>16} {'ms per step call (analytical, ann)':>34}")
    for p0 in (2e5, 5.85e6):
        closed, t_closed = run("analytical", args.loose, p0, "undrained", args)
        net, t_net = run("ann", args.loose, p0, "undrained", args)
        calls = [int(closed.newton_iterations.sum()), int(net.newton_iterations.sum())]
        difference = shear_difference(closed, net)
        row = {"part": "ann", "model": str(args.model), "alpha0_deg": args.loose, "p0": p0, "test": "undrained",
               "cells": int(closed.weights.size), "n_increments": [closed.n_increments, net.n_increments],
               "max_diff_over_p0": difference / p0,
               "iso_strain_at_p0": [float(r.eps11[r.stage == r.stage[0]][-1]) for r in (closed, net)], "max_diff_over_scale": difference / max(p0, float(closed.p.max())),
               "analytical_s": t_closed, "ann_s": t_net, "ratio": t_net / t_closed, "step_calls": calls,
               "ms_per_step_call": [1e3 * t_closed / calls[0], 1e3 * t_net / calls[1]],
               "n_ood": count(net, "n_ood"), "n_ood_checked": count(net, "n_ood_checked"),
               "load_average": os.getloadavg()[0]}
        print(f"{p0:9.3g} {'undrained':>9} {row['cells']:5d} {row['max_diff_over_p0']:13.3g} "
              f"{row['max_diff_over_scale']:8.3g} {t_closed:14.2f} {t_net:8.2f} {row['ratio']:16.2f} "
              f"{row['ms_per_step_call'][0]:16.3f}, {row['ms_per_step_call'][1]:.3f}", flush=True)
        print(json.dumps(row))


def ann3d_step(args) -> None:
    from homogenization.backends import make_cell_model
    from homogenization.material.orientation import orientations_3d
    from warp_hcell.mesostructures.builders import mesostructure_arg

    order, spins = rule(args.step_rule)
    frames = orientations_3d(order, spins)
    n = frames.weights.size
    localise = lambda eps: (frames.localisation @ eps).reshape(n, 3)  # noqa: E731
    meso = mesostructure_arg(f"hcell3d:alpha0={args.loose:g}").build(args.loose)
    options = {} if args.model is None else {"model": args.model}
    models = {"analytical": make_cell_model("analytical", dim=3), "ann": make_cell_model("ann", dim=3, **options)}
    iso, shear = localise(np.array([3e-4, 3e-4, 3e-4, 0, 0, 0])), localise(np.array([1e-4, -5e-5, -5e-5, 0, 0, 0]))
    states = {}
    for name, model in models.items():
        state = model.init_state(meso, n)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for k in range(110):
                state, response = model.step(state, iso if k < 10 else shear)
        states[name] = state
    ann = models["ann"]
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.repeats):
        for name, model in models.items():
            start = time.perf_counter()
            model.step(states[name], shear)
            times[name].append(time.perf_counter() - start)
    fast, ann.fast = ann.fast, None
    torch_s = [0.0] * max(3, args.repeats // 10)
    for k in range(len(torch_s)):
        start = time.perf_counter()
        ann.step(states["ann"], shear)
        torch_s[k] = time.perf_counter() - start
    ann.fast = fast
    ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    row = {"part": "ann3d-step", "model": str(ann.model_path), "rule": args.step_rule, "cells": n,
           "repeats": args.repeats, "analytical_ms": ms["analytical"], "ann_ms": ms["ann"],
           "ratio": ms["ann"] / ms["analytical"], "torch_path_ms": 1e3 * float(np.median(torch_s)),
           "contacts_per_cell": float(np.count_nonzero(np.any(states["ann"].shear_force != 0, axis=2)) / n),
           "load_average": os.getloadavg()[0]}
    print(f"{n} cells ({args.step_rule}), median step call over {args.repeats} interleaved repeats: analytical "
          f"{ms['analytical']:.2f} ms, ANN (compiled) {ms['ann']:.2f} ms, ratio ANN / analytical {row['ratio']:.2f}; "
          f"ANN torch path {row['torch_path_ms']:.1f} ms; load average {row['load_average']:.2f}", flush=True)
    print(json.dumps(row))


def main(argv: list[str] | None = None) -> int:
    parser = Parser(description=__doc__.splitlines()[2])
    parser.add_argument("--part", default=",".join(PARTS), help=f"comma list of {', '.join(PARTS)}")
    parser.add_argument("--eps-max", type=positive_float, default=0.15, help="axial strain of the shear stage [-]")
    parser.add_argument("--increment", type=positive_float, default=1e-4, help="axial strain increment [-]")
    parser.add_argument("--order", type=positive_int, default=11,
                        help="Lebedev order of the cell axes (accuracy, timing: cell by cell, any rule compares)")
    parser.add_argument("--spins", type=positive_int, default=4, help="spins per axis (accuracy, timing)")
    parser.add_argument("--rules", default="11x4,23x8,35x16", help="quadrature part: comma list of ORDERxSPINS rules")
    parser.add_argument("--reference", default="71x32",
                        help="quadrature part: the fine ORDERxSPINS rule, or none (doubling only)")
    parser.add_argument("--loose", type=positive_float, default=55.0, help="alpha0 of the loose cell [deg]")
    parser.add_argument("--dense", type=positive_float, default=47.0, help="alpha0 of the dense cell [deg], > 45")
    parser.add_argument("--threads", type=positive_int, default=None, help="DEM threads (None: its default)")
    parser.add_argument("--model", default=None, help="ann, ann3d-step parts: a 3D meso-ANN model (.pt)")
    parser.add_argument("--step-rule", default="53x16", help="ann3d-step part: the ORDERxSPINS rule of the cells")
    parser.add_argument("--repeats", type=positive_int, default=50, help="ann3d-step part: timed step calls per backend")
    args = parser.parse_args(argv)
    for text in [*args.rules.split(","), args.step_rule, *([] if args.reference == "none" else [args.reference])]:
        try:
            order, spins = rule(text)
        except ValueError:
            parser.error(f"rule {text!r} is not ORDERxSPINS, e.g. 23x8")
        if order not in LEBEDEV_ORDERS or spins < 1:
            parser.error(f"rule {text!r}: order must be one of {', '.join(map(str, LEBEDEV_ORDERS))}, spins >= 1")
    parts = [part.strip() for part in args.part.split(",")]
    unknown = [part for part in parts if part not in PARTS]
    if unknown:
        parser.error(f"--part {unknown[0]!r} is not one of {', '.join(PARTS)}")
    for part in parts:
        print(f"== {part}")
        {"accuracy": accuracy, "quadrature": quadrature, "timing": timing, "ann": ann, "ann3d-step": ann3d_step}[part](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
