"""python benchmarks/bench_short_runs.py [--repeats 3] [--increment 1e-4] [--eps-max 0.03] [--cpu N] [--cold] [--startup] [--gc] [--steps]: whole-process cost of short ANN runs.

Runs, as whole processes (``python -m homogenization.hmodel ...``, start-up, imports, model and
certificate loading, compilation or cache loading, the run and its output all counted), a
constant-volume ``hmodel biaxial`` (H-cell, 360 orientations, p0 = 2e5 N/m, inside the shipped
2D model's certificate) and an undrained ``hmodel triaxial`` (7 792 cells, p0 = 2e5 Pa) with
``--backend ann`` (A) and ``--backend analytical`` (B), interleaved A B A B ..., and prints for
each pair the wall and CPU (user + system of the child) seconds and the ratio A / B, then the
median and best ratio. ``--eps-max / --increment`` shear increments (300 by default) follow the
command's isotropic stage (its default increment).

Every process runs with Python's bytecode cache on (``PYTHONDONTWRITEBYTECODE`` removed from its
environment): the warm-up pair writes the ``.pyc`` files that a user's second run reads.

``--cold``: the ANN runs with an empty ``NUMBA_CACHE_DIR`` each time (the first run on a machine:
the kernels compiled, and the planar step's object, ``training.precompiled``), the closed form as usual.

``--startup``: instead, where a planar ANN process's CPU time goes, by phase, in fresh processes
(``--repeats`` of them): numpy's import, the ANN's modules and cell model (``AnnCell``), the first
step (the precompiled step's key and the object's loading; numba's import and set-up where the step falls
back to numba), the other 320 steps of 360 cells; then whether numba and llvmlite were imported, which
path the step took and which loader loaded it. Not the CLI: the phases of the run that differ from the closed form's.

``--cpu N``: every process runs on CPU N alone (``os.sched_setaffinity``; Linux), which narrows the spread of
single processes on a shared machine.

``--steps``: instead, where the two backends' time differs inside the tests' processes (``STEPS``, ``--repeats``
processes per backend): the cell model's steps (median milliseconds per call, their sum) against the whole run,
and the ANN's compiled parts timed alone on the state of its middle increment (features, perceptron, advance:
the physics after the network; best of 5 x 20 calls): how much of a step no network could remove.

``--gc``: instead, the planar test's two commands (``--repeats`` pairs) with the garbage collector's
collections counted by generation, and the seconds they took (``gc.callbacks``), beside each process's
CPU seconds.

The machine may be shared: the load average is printed before and after; CPU seconds are less
sensitive to other processes than wall seconds, not immune.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from warp_hcell.core.provenance import cpu_model

ROOT = Path(__file__).resolve().parents[1]


def commands(args, out: Path) -> dict[str, dict[str, list[str]]]:
    """Per test, the ANN and the closed-form command lines."""
    hmodel = [sys.executable, "-m", "homogenization.hmodel"]
    shear = ["--eps-max", f"{args.eps_max:g}", "--increment", f"{args.increment:g}", "--p0", "2e5", "--overwrite", "-q"]
    tests = {"biaxial 2D (360 cells)": ["biaxial", "--orientations", "360", *shear],
             "triaxial 3D (7792 cells)": ["triaxial", "--undrained", *shear]}
    return {test: {backend: [*hmodel, *argv, "--backend", backend, "--out", str(out / f"{argv[0]}_{backend}")]
                   for backend in ("ann", "analytical")}
            for test, argv in tests.items() if test.split()[0] in args.tests}


def child_environment() -> dict[str, str]:
    """This process's environment for the timed commands: the Agg backend of matplotlib, bytecode caching on."""
    env = {**os.environ, "MPLBACKEND": "Agg"}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def timed(argv: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall, CPU) seconds of one whole process; RuntimeError if it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


STARTUP = r"""
import json, sys, time
marks = [("start", time.process_time())]
def mark(name):
    marks.append((name, time.process_time()))
import numpy as np
mark("import numpy")
from homogenization.backends import make_cell_model
from homogenization.material.orientation import localise, orientations
from warp_hcell.mesostructures.hcell import h_cell
mark("import the ANN's modules")
cell = make_cell_model("ann", threads=1)
mark("AnnCell (model, certificate, OOD index)")
state = cell.init_state(h_cell(55.0), 360)
d_eps = localise(orientations(360), np.array([1e-5, -1e-5, 0.0]))
state, _ = cell.step(state, d_eps)
mark("first step (the precompiled step loaded, or numba's set-up)")
for _ in range(320):
    state, _ = cell.step(state, d_eps)
mark("320 more steps")
print(json.dumps({b[0]: round(b[1] - a[1], 4) for a, b in zip(marks, marks[1:])}))
print(f"numba imported: {'numba' in sys.modules}, llvmlite imported: {'llvmlite' in sys.modules}, "
      f"step: {cell.fast.step_path} {cell.fast.precompiled_loader}", file=sys.stderr)
"""


STEPS = r"""
import json, runpy, statistics, sys, time
import homogenization.backends as backends
calls, captured, make = [], {}, backends.make_cell_model
def timing(model, *args, **kwargs):
    model = make(model, *args, **kwargs)
    step = model.step
    def timed_step(*a, **k):
        start = time.perf_counter()
        try:
            return step(*a, **k)
        finally:
            calls.append(time.perf_counter() - start)
    model.step = timed_step
    fast = getattr(model, "fast", None)
    if fast is not None:
        increment = fast.increment
        def kept(*a, **k):  # the arguments of the middle step's increment (its copy: one step's median unmoved)
            if len(calls) == MIDDLE:
                captured["args"] = tuple(x.copy() for x in a[:4])
            return increment(*a, **k)
        fast.increment = kept
        captured["fast"] = fast
    return model
backends.make_cell_model = timing
MIDDLE = int(sys.argv[1])
sys.argv = ["hmodel", *sys.argv[2:]]
start = time.perf_counter()
try:
    runpy.run_module("homogenization.hmodel", run_name="__main__")
except SystemExit as exc:
    if exc.code:
        raise
row = {"run_s": time.perf_counter() - start, "steps": len(calls), "step_ms": 1e3 * statistics.median(calls),
       "steps_s": sum(calls)}
if "args" in captured:
    from training.inference import _cells_last
    fast, (size, free, shear, d_eps) = captured["fast"], captured["args"]
    size, free, shear, d_eps = _cells_last(size), _cells_last(free), _cells_last(shear), d_eps
    work, result = fast._workspace(d_eps.shape[0]), fast._result(d_eps.shape[0])
    parts = {"features": lambda: fast._features(size, free, shear, d_eps, fast.cells, fast.law, fast.scaling,
                                                work.before),
             "perceptron": lambda: fast._forward(fast.perceptron.weight, fast.perceptron.bias, work.before.feats,
                                                 work.layers),
             "advance": lambda: fast._advance(size, free, shear, d_eps, work.layers[-1], fast.cells, fast.law,
                                              fast.scaling, work.before, result)}
    for name, call in parts.items():
        call()
        best = []
        for _ in range(5):
            start = time.perf_counter()
            for _ in range(20):
                call()
            best.append((time.perf_counter() - start) / 20)
        row[name + "_ms"] = 1e3 * min(best)
print(json.dumps(row))
"""


def steps(args, out: Path) -> None:
    """Per test, ``args.repeats`` processes of each backend under ``STEPS``: the cell model's step (median ms per
    call), the sum of its calls against the whole run, and for the ANN its compiled parts alone; then the ratio of
    the steps and what the ANN's features and advance alone cost against the closed form's whole step."""
    env = child_environment()
    middle = str(round(args.eps_max / args.increment) // 2)
    for test, argv in commands(args, out).items():
        print(f"== {test}", flush=True)
        rows = {}
        for backend in ("ann", "analytical"):
            timed(argv[backend], env)  # warm-up, as in the timed pairs
        for k in range(args.repeats):
            for backend in ("ann", "analytical"):
                done = subprocess.run([sys.executable, "-c", STEPS, middle, *argv[backend][3:]], cwd=ROOT, env=env,
                                      capture_output=True, text=True, check=True)
                row = json.loads(done.stdout.strip().splitlines()[-1])
                rows.setdefault(backend, []).append(row)
                print(f"process {k + 1}, {backend}: " + ", ".join(f"{key} {value:.3f}" if isinstance(value, float)
                                                                 else f"{key} {value}" for key, value in row.items()),
                      flush=True)
        median = {backend: {key: statistics.median(r[key] for r in rs) for key in rs[0]}
                  for backend, rs in rows.items()}
        ann, closed = median["ann"], median["analytical"]
        if "features_ms" not in ann:
            raise SystemExit(f"{test}: the ANN took no compiled step at its middle increment (increment {middle})")
        physics = ann["features_ms"] + ann["advance_ms"]
        print(f"{test}: medians of {args.repeats}: step ANN {ann['step_ms']:.3f} ms, closed form "
              f"{closed['step_ms']:.3f} ms (ratio {ann['step_ms'] / closed['step_ms']:.2f}); steps "
              f"{ann['steps_s']:.2f} s of a {ann['run_s']:.2f}-s "
              f"run against {closed['steps_s']:.2f} of {closed['run_s']:.2f} s; ANN parts alone: features "
              f"{ann['features_ms']:.3f}, perceptron {ann['perceptron_ms']:.3f}, advance {ann['advance_ms']:.3f} ms; "
              f"features + advance (no network) {physics:.3f} ms = {physics / closed['step_ms']:.2f} of the closed "
              f"form's step", flush=True)


GC_WATCH = r"""
import atexit, gc, json, runpy, sys, time
stats, start = {0: [0, 0.0], 1: [0, 0.0], 2: [0, 0.0]}, [0.0]
def watch(phase, info):
    if phase == "start":
        start[0] = time.perf_counter()
    else:
        stats[info["generation"]][0] += 1
        stats[info["generation"]][1] += time.perf_counter() - start[0]
gc.callbacks.append(watch)
atexit.register(lambda: print(json.dumps({"collections": {g: n for g, (n, _) in stats.items()},
                                          "seconds": {g: round(t, 3) for g, (_, t) in stats.items()}}), file=sys.stderr))
sys.argv = ["hmodel", *sys.argv[1:]]
runpy.run_module("homogenization.hmodel", run_name="__main__")
"""


def gc_counts(args, out: Path) -> None:
    """The planar test's ANN and closed-form processes (``args.repeats`` pairs) with their garbage collections
    counted by generation (``GC_WATCH``): collections, seconds in them, and the process's CPU seconds."""
    env = child_environment()
    argv = commands(argparse.Namespace(**{**vars(args), "tests": ["biaxial"]}), out)["biaxial 2D (360 cells)"]
    for backend in ("ann", "analytical"):  # warm-up, as in the timed pairs
        timed(argv[backend], env)
    for k in range(args.repeats):
        for backend in ("ann", "analytical"):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            done = subprocess.run([sys.executable, "-c", GC_WATCH, *argv[backend][3:]], cwd=ROOT, env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=True)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
            print(f"pair {k + 1}, {backend}: {done.stderr.strip().splitlines()[-1]}, CPU {cpu:.2f} s", flush=True)


def startup(args) -> None:
    """CPU seconds of each phase of a planar ANN process (``STARTUP``), ``args.repeats`` processes, whether numba
    and llvmlite were imported, the step's path and its loader."""
    env = child_environment()
    runs, paths = [], set()
    for _ in range(args.repeats):
        done = subprocess.run([sys.executable, "-c", STARTUP], cwd=ROOT, env=env, capture_output=True, text=True,
                              check=True)
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        paths.add(done.stderr.strip().splitlines()[-1])
    phases = "; ".join(f"{name} {statistics.median(r[name] for r in runs):.3f}" for name in runs[0])
    total = statistics.median(sum(r.values()) for r in runs)
    print(f"CPU seconds, median of {len(runs)} processes: {phases}; sum {total:.3f} ({', '.join(sorted(paths))})",
          flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="pairs (A, B) per test")
    parser.add_argument("--increment", type=float, default=1e-4, help="shear strain increment [-]")
    parser.add_argument("--eps-max", type=float, default=0.03, help="shear strain of the test [-]")
    parser.add_argument("--tests", nargs="+", choices=("biaxial", "triaxial"), default=["biaxial", "triaxial"])
    parser.add_argument("--cold", action="store_true", help="ANN runs with an empty NUMBA_CACHE_DIR each time")
    parser.add_argument("--startup", action="store_true", help="only the CPU time of a planar ANN process by phase")
    parser.add_argument("--gc", action="store_true", help="only the planar test's garbage collections, both backends")
    parser.add_argument("--steps", action="store_true",
                        help="only the steps' time inside the processes, and the ANN's compiled parts alone")
    parser.add_argument("--cpu", type=int, default=None,
                        help="run every process on this CPU alone (Linux; less spread between processes)")
    args = parser.parse_args()
    if args.cpu is not None:
        if not hasattr(os, "sched_setaffinity") or args.cpu not in os.sched_getaffinity(0):
            parser.error(f"--cpu {args.cpu}: not a CPU this process may run on")
        os.sched_setaffinity(0, {args.cpu})  # the timed processes inherit it
    print(f"load average (1, 5, 15 min): {os.getloadavg()}; {os.cpu_count()} CPUs ({cpu_model()})"
          + ("" if args.cpu is None else f"; every process on CPU {args.cpu}"), flush=True)
    if args.startup:
        startup(args)
        print(f"load average after: {os.getloadavg()}", flush=True)
        return
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(scratch)
        if args.steps:
            steps(args, out)
            print(f"load average after: {os.getloadavg()}", flush=True)
            return
        if args.gc:
            gc_counts(args, out)
            print(f"load average after: {os.getloadavg()}", flush=True)
            return
        env = child_environment()
        for test, argv in commands(args, out).items():
            print(f"== {test}: {' '.join(Path(a).name if a == sys.executable else a for a in argv['ann'])}", flush=True)
            for backend in ("ann", "analytical"):  # warm-up: caches (numba, Warp, the OS's files) as a user's second run
                timed(argv[backend], env)
            rows = []
            for k in range(args.repeats):
                ann_env = env
                if args.cold:
                    ann_env = {**env, "NUMBA_CACHE_DIR": tempfile.mkdtemp(dir=scratch)}
                a = timed(argv["ann"], ann_env)
                b = timed(argv["analytical"], env)
                rows.append({"ann_wall": a[0], "ann_cpu": a[1], "analytical_wall": b[0], "analytical_cpu": b[1],
                             "ratio_wall": a[0] / b[0], "ratio_cpu": a[1] / b[1]})
                print(f"pair {k + 1}: ANN {a[0]:.2f} s wall, {a[1]:.2f} s CPU; closed form {b[0]:.2f} s wall, "
                      f"{b[1]:.2f} s CPU; ratio ANN / closed form {a[0] / b[0]:.2f} wall, {a[1] / b[1]:.2f} CPU",
                      flush=True)
            summary = {key: (statistics.median(r[key] for r in rows), min(r[key] for r in rows))
                       for key in ("ratio_wall", "ratio_cpu")}
            print(f"{test}: ratio ANN / closed form, whole process, median (best) of {args.repeats}: "
                  f"wall {summary['ratio_wall'][0]:.2f} ({summary['ratio_wall'][1]:.2f}), "
                  f"CPU {summary['ratio_cpu'][0]:.2f} ({summary['ratio_cpu'][1]:.2f})", flush=True)
            print(json.dumps({"test": test, "cold": args.cold, "increment": args.increment, "eps_max": args.eps_max,
                              "pairs": rows}), flush=True)
    print(f"load average after: {os.getloadavg()}", flush=True)


if __name__ == "__main__":
    main()
