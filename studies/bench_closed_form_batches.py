"""python studies/bench_closed_form_batches.py [RESULT.json] [--rule 35x12s] [--sets 15] [--tests 50] [--repeats 2]

The Dobrany forward model (``forward.simulate``) on one population of parameter sets, twice per repeat in turn in
one process: with the closed form's large-batch paths (the compiled tangent average and cell volume, the equilibrium
iteration narrowed to its unconverged cells: ``homogenised.COMPILED_TANGENT_FROM_CELLS``,
``mesostructure.COMPILED_VOLUME_FROM_CELLS``, ``analytical.NARROW_FROM_CELLS``) and with every threshold set out of
reach (the numpy code of small batches). Prints each run's wall time, the ratio fast / numpy (best of the repeats)
and whether q and eps_v of every set and test are the same bytes. The sets: RESULT's posterior mean (default the
35 x 12 refit of docs/studies/calibration_dobrany_rule_convergence.md) with kn x 0.85-1.15 and phi_g 30-40 deg
spread over ``--sets``; ``--tests`` the confining pressures [kPa] of the Dobrany tests to run. Writes
studies/results/bench_closed_form_batches_RULE.txt. Run it on one core (``taskset -c 1``) for timings.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import RESULTS, dobrany_tests, sensitivity_setup  # noqa: E402
from homogenization.backends import analytical  # noqa: E402
from homogenization.calibration import forward  # noqa: E402
from homogenization.material import homogenised  # noqa: E402
from warp_hcell.mesostructures import mesostructure  # noqa: E402

THRESHOLDS = ((homogenised, "COMPILED_TANGENT_FROM_CELLS"), (mesostructure, "COMPILED_VOLUME_FROM_CELLS"),
              (analytical, "NARROW_FROM_CELLS"))
"""The modules and names of the large-batch thresholds."""

DEFAULT_RESULT = RESULTS / "calibration_dobrany_product_50_100_mv_n0_ms_cs05_kn08_35x12s.json"


def run(tests: dict, params: dict, settings, fast: bool) -> tuple[float, list[np.ndarray]]:
    """(wall [s], the q and eps_v arrays of every test) of the population with the large-batch paths on or off."""
    saved = [getattr(module, name) for module, name in THRESHOLDS]
    if not fast:
        for module, name in THRESHOLDS:
            setattr(module, name, 10**12)
    try:
        started = time.perf_counter()
        curves = []
        for test in tests.values():
            with np.errstate(all="ignore"):
                c = forward.simulate(test, params, settings)
            curves += [c.q, c.eps_v]
        return time.perf_counter() - started, curves
    finally:
        for (module, name), value in zip(THRESHOLDS, saved):
            setattr(module, name, value)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", type=Path, nargs="?", default=DEFAULT_RESULT, help="a calibration study's JSON")
    parser.add_argument("--rule", default="35x12s", help="orientation rule ORDERxSPINS[a|s]")
    parser.add_argument("--sets", type=int, default=15, help="parameter sets in the population")
    parser.add_argument("--tests", default="50", help="comma-separated confining pressures [kPa] of the tests to run")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each kind, in turn")
    args = parser.parse_args(argv)
    if not args.result.is_file() or args.sets < 1 or args.repeats < 1:
        parser.exit(2, f"{parser.prog}: error: needs an existing RESULT.json, --sets >= 1 and --repeats >= 1\n")
    pressures = {float(p) * 1e3 for p in args.tests.split(",")}
    tests = {k: t for k, t in dobrany_tests().items() if round(t.p0) in {round(p) for p in pressures}}
    if not tests:
        parser.exit(2, f"{parser.prog}: error: no Dobrany test at --tests {args.tests} kPa\n")
    n = args.sets
    variants = [(0.85 + 0.3 * i / max(n - 1, 1), 30.0 + 10.0 * i / max(n - 1, 1)) for i in range(n)]
    _, params, settings = sensitivity_setup(args.result, args.rule, variants, ("kn_factor", "phi_g"), kn_factor=0)
    params.pop("kn_factor")
    lines = [f"# python studies/bench_closed_form_batches.py {' '.join(argv if argv is not None else sys.argv[1:])}",
             f"{n} sets x {len(tests)} test(s) ({', '.join(tests)}), rule {args.rule}"]
    print(lines[-1], flush=True)
    walls: dict[bool, list[float]] = {True: [], False: []}
    reference = None
    same = True
    for repeat in range(args.repeats):
        for fast in (False, True):
            wall, curves = run(tests, params, settings, fast)
            walls[fast].append(wall)
            reference = reference or curves
            same &= all(a.tobytes() == b.tobytes() for a, b in zip(reference, curves))
            lines.append(f"repeat {repeat + 1}: {'large-batch paths' if fast else 'numpy code     '} {wall:7.1f} s")
            print(lines[-1], flush=True)
    ratio = min(walls[True]) / min(walls[False])
    lines.append(f"ratio large-batch paths / numpy code, best of {args.repeats}: {ratio:.3f}; "
                 f"q and eps_v of every set and test the same bytes: {same}")
    print(lines[-1])
    (RESULTS / f"bench_closed_form_batches_{args.rule}.txt").write_text("\n".join(lines) + "\n")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
