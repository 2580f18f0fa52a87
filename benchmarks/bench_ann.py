"""python benchmarks/bench_ann.py [--model PATH] [--cells 360] [--repeats 1000] [--widths W ...]: ANN vs analytical increment, side by side.

Prints, on one torch thread and in one run (the machine is shared: the load average is
printed with the numbers):

1. the median time of one ``step`` of ``--cells`` H-cells (alpha0 = 55 deg, after an
   isotropic compression, constant-volume-like increments of 1e-5) for the analytical and
   the ANN backend (``AnnCell.step``: compiled float64 physics around the float32
   perceptron), interleaved, and their ratio; for the ANN also
   the torch autograd path without tangent (``MesoNet.advance`` under inference mode, the
   implementation before the compiled one), the network call alone
   (``MesoNet.displacement``) and the step with its autograd tangent; with ``--widths``, in
   the same interleaved loop, the step of networks of other hidden widths (the model's inputs,
   random weights: the cost of a width, ``homogenization.learning.active.WIDTH_LADDER``);
   with ``--parts``, where the ANN step's time goes: the median of each part called alone (the
   whole ``AnnCell.step``, ``FastAdvance.increment``, its compiled call (``fast_increment.step``), the
   three kernels it runs called one after the other, and the
   features, the perceptron, each layer with and without its tanh, and the advance kernel apart), at
   ``--cells`` cells and at one cell (the fixed cost of each call); with ``--step3d-repeats`` N > 0, beside
   it the spatial step's ratio (``benchmarks/bench_triaxial.py --part ann3d-step --repeats N``: the shipped
   3D model on 7 792 ten-sphere cells);
2. unless ``--skip-run``: one JSON line per biaxial test (isotropic compression to p0, then
   constant-volume, and/or drained (``--tests``), shear to ``--eps-max``; ``reversal``:
   constant volume to eps1 = +``--reversal-strain``, then back to -``--reversal-strain``,
   compared increment by increment) run with the
   ANN and its reference through ``homogenization.element_test.driver``: the analytical backend for the
   H-cell, the DEM with the same file for ``--mesostructure``; max |p - p_ref| and
   |q - q_ref| over the shear stage as fractions of p0, run times, and the ANN's counts of
   contact-law branches.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time

import tempfile
from pathlib import Path

import numpy as np
import torch

from homogenization.element_test import driver, programme as programmes
from homogenization.backends import make_cell_model
from homogenization.material.orientation import localise, orientations
from training.checkpoint import load_checkpoint, save_checkpoint
from training.network import MesoNet
from training.config import hidden_widths
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.core.parameters import CellDefaults
from warp_hcell.core.provenance import cpu_model


def _time(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--model", default=None, help="model state_dict (default: the shipped model)")
    parser.add_argument("--cells", type=int, default=360, help="cells (orientations) per increment")
    parser.add_argument("--repeats", type=int, default=1000, help="timed increments per backend")
    parser.add_argument("--skip-run", action="store_true", help="only time single increments (H-cell)")
    parser.add_argument("--increments", type=float, nargs="+", default=[1e-4, 1e-5],
                        help="increments of the biaxial runs (isotropic and shear stages) [-]")
    parser.add_argument("--p0", type=float, nargs="+", default=[CellDefaults.p0, 2e5],
                        help="confining pressures of the biaxial runs [N/m]")
    parser.add_argument("--alpha0", type=float, nargs="+", default=[55.0], help="initial opening angles [deg]")
    parser.add_argument("--eps-max", type=float, default=0.2, help="eps1 at the end of the shear stage [-]")
    parser.add_argument("--tests", choices=("constant-volume", "drained", "both", "reversal"),
                        default="constant-volume", help="biaxial tests to run")
    parser.add_argument("--reversal-strain", type=float, default=0.05,
                        help="reversal test: eps1 of the turn, then back to minus it [-]")
    parser.add_argument("--mesostructure", default=None,
                        help="mesostructure file: compare the ANN (--model trained on it) with the DEM")
    parser.add_argument("--widths", nargs="+", type=hidden_widths, default=[],
                        help="also time networks of these hidden widths (e.g. 48,48 40,40,40): --model's inputs, "
                             "normalisation and schema, random weights (timing only: the active-learning ladder)")
    parser.add_argument("--parts", action="store_true", help="also time the parts of the ANN step, each alone")
    parser.add_argument("--step3d-repeats", type=int, default=0,
                        help="also time the 3D step (bench_triaxial.py --part ann3d-step) with this many repeats (0: no)")
    args = parser.parse_args()
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; CPU: {cpu_model()}")
    if args.parts and args.mesostructure is None:
        for n in (args.cells, 1):
            time_parts(args.model, n, args.repeats)
    if args.mesostructure is None:
        time_increments(args)
    if args.step3d_repeats > 0:
        time_step3d(args.step3d_repeats)
    if not args.skip_run:
        for case in _cases(args):
            print(json.dumps(compare(case, args.model, args.mesostructure, args.cells)), flush=True)
    print(f"load average after: {os.getloadavg()}")


def time_increments(args) -> None:
    """Median time of one H-cell increment of the analytical and the ANN backend, interleaved."""
    models = {"analytical": make_cell_model("analytical"), "ann": make_cell_model("ann", model=args.model, threads=1)}
    scratch = tempfile.TemporaryDirectory()
    for widths in args.widths:
        models[f"ann {'x'.join(map(str, widths))}"] = make_cell_model(
            "ann", model=_random_model(models["ann"].model_path, widths, Path(scratch.name)), threads=1)
    models["ann"].net  # noqa: B018 (the torch network of the torch-path timings below; sets torch's threads)
    print(f"torch threads: {torch.get_num_threads()}")
    orient = orientations(args.cells)
    iso = localise(orient, np.array([2e-5, 2e-5, 0.0]))
    d_eps = localise(orient, np.array([1e-5, -1e-5, 0.0]))
    states = {}
    for name, model in models.items():
        state = model.init_state(h_cell(55.0), args.cells)
        for _ in range(100):
            state, _ = model.step(state, iso)
        states[name] = state
    times: dict[str, list[float]] = {name: [] for name in models}
    for _ in range(args.repeats):
        for name, model in models.items():
            times[name].append(_time(lambda: model.step(states[name], d_eps)))
    ann = models["ann"]
    tensors = [torch.from_numpy(a) for a in states["ann"]]
    d = torch.from_numpy(d_eps)
    with torch.inference_mode():
        net_ms = 1e3 * np.median([_time(lambda: ann.net.displacement(*tensors, d)) for _ in range(args.repeats)])
        torch_ms = 1e3 * np.median([_time(lambda: ann.net.advance(*tensors, d)) for _ in range(args.repeats // 4)])
    tangent_ms = 1e3 * np.median([_time(lambda: ann.step(states["ann"], d_eps, with_tangent=True)) for _ in range(100)])
    ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    print(f"{args.cells} cells, median per increment: analytical step {ms['analytical']:.3f} ms, "
          f"ANN step {ms['ann']:.3f} ms (torch path without tangent {torch_ms:.3f} ms; network call {net_ms:.3f} ms; "
          f"with tangent {tangent_ms:.3f} ms); ratio ANN / analytical = {ms['ann'] / ms['analytical']:.2f} "
          f"(torch path {torch_ms / ms['analytical']:.2f})",
          flush=True)
    for name in list(models)[2:]:
        print(f"{name}: step {ms[name]:.3f} ms, ratio / analytical = {ms[name] / ms['analytical']:.2f}", flush=True)
    scratch.cleanup()


def time_step3d(repeats: int) -> None:
    """The 3D step's ratio (``bench_triaxial.ann3d_step``, its defaults and ``repeats``), printed beside the 2D one."""
    spec = importlib.util.spec_from_file_location("bench_triaxial", Path(__file__).with_name("bench_triaxial.py"))
    triaxial = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(triaxial)
    options = argparse.Namespace(step_rule="53x16", loose=55.0, model=None, repeats=repeats)
    print("3D step (bench_triaxial.py --part ann3d-step): ", end="", flush=True)
    triaxial.ann3d_step(options)


def _median_us(fn, repeats: int) -> float:
    return 1e6 * float(np.median([_time(fn) for _ in range(repeats)]))


def time_parts(model, n: int, repeats: int) -> None:
    """Median time [us] of each part of the ANN step of ``n`` H-cells (as ``time_increments``), each called alone."""
    from training.fast_tables import Advanced  # noqa: PLC0415
    from training.fast_features import features  # noqa: PLC0415
    from training.fast_increment import advance, step  # noqa: PLC0415
    from training.inference import _cells_last, _Compiled  # noqa: PLC0415
    from training.perceptron import dense, forward_layers  # noqa: PLC0415

    ann = make_cell_model("ann", model=model, threads=1)
    fast = ann.fast
    orient = orientations(n)
    state = ann.init_state(h_cell(55.0), n)
    for _ in range(100):
        state, _ = ann.step(state, localise(orient, np.array([2e-5, 2e-5, 0.0])))
    d_eps = np.ascontiguousarray(localise(orient, np.array([1e-5, -1e-5, 0.0])))
    size, free, shear = (_cells_last(a) for a in state)
    work = fast._workspace(n)
    n_free = free.shape[0]
    result = Advanced(np.empty((2, n)), np.empty((n_free, n)), np.empty(shear.shape), np.empty((n, 2, 2)), np.empty(n),
                      *np.empty((4, n), dtype=bool), np.empty(n, dtype=np.int64), np.empty((n_free, n), dtype=bool))
    tables = (fast.cells, fast.law, fast.scaling)
    # entry points, as FastAdvance calls them
    features_entry, forward_entry, advance_entry = _Compiled(features), _Compiled(forward_layers), _Compiled(advance)
    step_entry, counts = _Compiled(step), np.empty(5, dtype=np.int64)
    weights, biases, layers = fast.perceptron.weight, fast.perceptron.bias, work.layers
    inputs = (work.before.feats, *layers[:-1])
    last = len(weights) - 1
    def compiled() -> None:
        features_entry(size, free, shear, d_eps, *tables, work.before)
        forward_entry(weights, biases, work.before.feats, layers)
        advance_entry(size, free, shear, d_eps, layers[-1], *tables, work.before, result)

    parts = {"AnnCell.step": lambda: ann.step(state, d_eps),
             "FastAdvance.increment": lambda: fast.increment(*state, d_eps),
             "its compiled call": lambda: step_entry(size, free, shear, d_eps, *tables, weights, biases, work.before,
                                                     layers, result, counts),
             "the three kernels apart": compiled,
             "features apart": lambda: features_entry(size, free, shear, d_eps, *tables, work.before),
             "perceptron apart": lambda: forward_entry(weights, biases, work.before.feats, layers),
             **{f"layer {k} (tanh: {k < last})":
                (lambda k=k: dense(weights[k], biases[k], inputs[k], layers[k], k < last)) for k in range(last + 1)},
             **{f"layer {k} without tanh": (lambda k=k: dense(weights[k], biases[k], inputs[k], layers[k], False))
                for k in range(last)},
             "advance apart": lambda: advance_entry(size, free, shear, d_eps, layers[-1], *tables, work.before, result)}
    for fn in parts.values():
        fn()
    fast.increment(*state, d_eps)  # leaves the layers as the network's outputs
    print(f"{n} cells, parts alone, median of {repeats} calls [us]: "
          + "; ".join(f"{name} {_median_us(fn, repeats):.1f}" for name, fn in parts.items()), flush=True)


def _random_model(model: Path, widths: tuple[int, ...], folder: Path) -> Path:
    """A model file of hidden ``widths`` with ``model``'s schema, active pairs and normalisation
    and random weights (seed 0), for timing."""
    net, meta = load_checkpoint(model)
    torch.manual_seed(0)
    wide = MesoNet(net.schema, net.active, widths, net.load_features)
    wide.set_normalisation(net.feature_mean, net.feature_std, net.rate_mean, net.rate_std)
    path = folder / f"{'x'.join(map(str, widths))}.pt"
    save_checkpoint(path, wide, {k: v for k, v in meta.items() if k not in ("architecture", "normalisation")})
    return path


def _cases(args) -> list[dict]:
    alphas = args.alpha0
    if args.tests == "reversal":
        return [{"p0": p0, "increment": inc, "reversal": args.reversal_strain, "alpha0": alpha0}
                for alpha0 in args.alpha0 for p0 in args.p0 for inc in args.increments]
    return [{"p0": p0, "increment": inc, "drained": drained, "alpha0": alpha0, "eps_max": args.eps_max}
            for drained in {"constant-volume": [False], "drained": [True], "both": [False, True]}[args.tests]
            for alpha0 in alphas
            for p0 in args.p0 for inc in args.increments]


def reversal_programme(p0: float, turn: float, increment: float) -> programmes.Programme:
    """Isotropic compression to p0, constant volume to eps1 = +turn, then back to eps1 = -turn.

    Args:
        p0: confining pressure [N/m]; turn: eps1 of the turn [-], > 0 (compression
            positive); increment: strain increment of every stage [-].
    """
    n = programmes.n_increments_for(turn, increment)
    return (programmes.isotropic(p0, increment=increment), programmes.constant_volume_biaxial(turn, n, label="load"),
            programmes.proportional_strain(-2.0 * turn, 2.0 * turn, 2 * n, label="unload"))


def _shear_stage(record):
    """Shear-stage eps1 counted from its start [-], p and q [N/m], and p at the end of the isotropic stage."""
    shear = record.stage != record.stage[0]
    start = record.eps11[~shear][-1]
    return record.eps11[shear] - start, record.p[shear], record.q[shear], record.p[~shear][-1]


def compare(case: dict, model, mesostructure, n_cells: int) -> dict:
    """One biaxial test with the ANN and its reference (analytical for the H-cell, DEM for a file).

    Returns the case, max |p_ann - p_ref| / p0 and max |q_ann - q_ref| / p0 over the shear
    stage (ANN interpolated at the reference's eps1), the run times and the ANN's summed
    diagnostics (contact-law branch counts), or the error that stopped a run.
    """
    meso = load_mesostructure(mesostructure) if mesostructure else h_cell(case["alpha0"])
    reference = ("dem", {}) if mesostructure else ("analytical", {})
    if "reversal" in case:
        programme = reversal_programme(case["p0"], case["reversal"], case["increment"])
    else:
        programme = programmes.biaxial(case["p0"], case["eps_max"], case["increment"], iso_increment=case["increment"],
                                    drained=case["drained"])
    out: dict = {"case": {**case, "mesostructure": str(mesostructure) if mesostructure else "h-cell (builder)",
                          "reference": reference[0], "n_cells": n_cells}}
    records = {}
    for name, options in (reference, ("ann", {"model": model, "threads": 1})):
        options = {k: v for k, v in options.items() if v is not None}
        start = time.perf_counter()
        try:
            records[name] = driver.run(make_cell_model(name, **options), programme, mesostructure=meso,
                                       n_orientations=n_cells, progress=False)
        except driver.ControlError as exc:
            return {**out, "error": f"{name}: {exc}"}
        out[f"seconds_{name}"] = round(time.perf_counter() - start, 1)
    e_ref, p_ref, q_ref, _ = _shear_stage(records[reference[0]])
    e_ann, p_ann, q_ann, p_iso = _shear_stage(records["ann"])
    if "reversal" in case:  # eps1 goes back: same strain-controlled increments, compared one by one
        n = min(e_ref.size, e_ann.size)
        out["max_dp_over_p0"] = float(np.abs(p_ann[:n] - p_ref[:n]).max() / case["p0"])
        out["max_dq_over_p0"] = float(np.abs(q_ann[:n] - q_ref[:n]).max() / case["p0"])
        out["increments_compared"] = int(n)
    else:
        out["max_dp_over_p0"] = float(np.abs(np.interp(e_ref, e_ann, p_ann) - p_ref).max() / case["p0"])
        out["max_dq_over_p0"] = float(np.abs(np.interp(e_ref, e_ann, q_ann) - q_ref).max() / case["p0"])
    out["ann_eps1_reached"] = float(e_ann[-1])
    out["ann_diagnostics"] = {k: float(np.nansum(v)) for k, v in records["ann"].diagnostics.items()
                              if not k.endswith("_all_calls")}
    return out


if __name__ == "__main__":
    main()
