"""python studies/plane_composed_ann_cost.py [--rule 53x16] [--repeats 30]: what a ten-sphere cell run as its two
planes of the planar meso-ANN would cost per step, against the 3D closed form.

The closed form solves the ten-sphere cell as two planar H-cells, (n, t1) and (n, t2), that share the axial grains
(``homogenization.backends.analytical``; they decouple while no cross-plane pair touches). A 3D ANN built the same
way would step the shipped planar model on 2 n cells, plane A taking (d_eps_n, d_eps_t1) and plane B (d_eps_n,
d_eps_t2), before combining the planes. This script times, interleaved on the same path as
``bench_triaxial.py --part ann3d-step`` (10 isotropic increments of 3e-4, then 100 of shear (1e-4, -5e-5, -5e-5),
then the timed one): the 3D closed form on n cells, the planar closed form and the planar ANN (one thread) on
the 2 n plane cells, and the closed form's response of the ten-sphere cells from their planes' states (the planes'
moments combined and the volume of the polyhedron through the ten centres, which a composed step needs too). The
planar ANN's step plus that response is a lower bound of the composed step. Prints the medians [ms] and their ratios to the 3D closed form's step, and
one JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import numpy as np

from homogenization.backends import make_cell_model
from homogenization.material.orientation import orientations_3d
from warp_hcell.mesostructures.builders import mesostructure_arg
from warp_hcell.mesostructures.hcell import h_cell

ISOTROPIC = np.array([3e-4, 3e-4, 3e-4, 0.0, 0.0, 0.0])
SHEAR = np.array([1e-4, -5e-5, -5e-5, 0.0, 0.0, 0.0])


def planes(d_eps: np.ndarray) -> np.ndarray:
    """The plane cells' strain increments (2 n, 2): (d_eps_n, d_eps_t1) of plane A, then (d_eps_n, d_eps_t2) of B."""
    return np.concatenate([d_eps[:, [0, 1]], d_eps[:, [0, 2]]])


def walk(model, state, iso: np.ndarray, shear: np.ndarray):
    """``state`` after 10 increments ``iso`` and 100 ``shear`` (the closed form warns where a cell opens)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for k in range(110):
            state, _ = model.step(state, iso if k < 10 else shear)
    return state


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rule", default="53x16", help="the ORDERxSPINS orientation rule of the 3D cells")
    parser.add_argument("--repeats", type=int, default=30, help="timed step calls per model, interleaved")
    args = parser.parse_args()
    order, spins = (int(v) for v in args.rule.split("x"))
    frames = orientations_3d(order, spins)
    n = frames.weights.size
    iso, shear = ((frames.localisation @ e).reshape(n, 3) for e in (ISOTROPIC, SHEAR))
    closed3 = make_cell_model("analytical", dim=3)
    models = {"closed form 3D": (closed3, walk(closed3, closed3.init_state(
        mesostructure_arg("hcell3d:alpha0=55").build(55.0), n), iso, shear), shear)}
    for name, model in (("closed form, planes", make_cell_model("analytical")),
                        ("ANN, planes", make_cell_model("ann", threads=1))):
        models[name] = (model, walk(model, model.init_state(h_cell(55.0), 2 * n), planes(iso), planes(shear)),
                        planes(shear))
    calls = {name: (lambda m=model, s=state, d=d_eps: m.step(s, d)) for name, (model, state, d_eps) in models.items()}
    calls["response 3D"] = lambda s=models["closed form 3D"][1]: closed3.volume(s)
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(args.repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
    base = ms["closed form 3D"]
    ms["lower bound, composed ANN"] = ms["ANN, planes"] + ms["response 3D"]
    print(f"{n} ten-sphere cells ({args.rule}), {2 * n} plane cells, median of {args.repeats} interleaved calls: "
          + ", ".join(f"{name} {value:.2f} ms ({value / base:.2f})" for name, value in ms.items()), flush=True)
    print(json.dumps({"rule": args.rule, "cells": n, "repeats": args.repeats, "ms": ms,
                      "composed_ann_lower_bound_over_closed_form_3d": ms["lower bound, composed ANN"] / base,
                      "load_average": os.getloadavg()[0]}))


if __name__ == "__main__":
    main()
