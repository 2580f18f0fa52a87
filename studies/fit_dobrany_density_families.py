"""python studies/fit_dobrany_density_families.py --spread S [--fit-spread] [--base RESULT.json] [--start-run DIR]
                       [--start-scales NAME=F1,...] [--steps 8] [--workers 1] [--tag T] [--rules 15x4s,35x12s]
                       [--evaluate-only --result-tag R]

The Dobrany fit of a base study result (default: the 50 + 100 kPa kn x 0.8 start on Lebedev 15 x 4 staggered,
``calibration_dobrany_product_50_100_mv_n0_ms_cs05_kn08_15x4s``: its ``hmodel calibrate`` command, started at its
posterior mean, or at the posterior mean of the calibration in ``--start-run``) run again in this process with the
density families (``--alpha0-spread S``: alpha0_spread fixed at S [deg]; ``--fit-spread``: alpha0_spread calibrated,
started at S; ``--start-scales``: ``hmodel calibrate``'s), then the three tests at the new posterior mean on the orientation rules ``--rules``
(``screen_dobrany_dilation_delay.shape``: q and volume errors, the turn to dilation, the first peak, the highest q and
its plateau, the renewal's clips).
The last rule's curves go to ``..._figure.json`` for ``calibration_dobrany_product.py --splits-figure``.
``--evaluate-only``: the evaluation alone, of the fit already in the folder, its results suffixed ``_R``. Writes
studies/results/fit_dobrany_density_families_SPLIT_TAG.{json,txt}; the calibration's folder is
runs/dobrany_product/SPLIT_families_TAG.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibration_dobrany_product import (MOBILISATION_PRIOR, MOBILISATION_VOID_PRIOR, PRIOR, RESULTS,  # noqa: E402
                                        RUNS, dobrany_tests)
from scan_dobrany_prediction_rules import plateau  # noqa: E402
from screen_dobrany_dilation_delay import shape, text  # noqa: E402

from homogenization.calibration import forward, posterior as post_mod  # noqa: E402
from homogenization.material.opening_spread import NAME as SPREAD  # noqa: E402
from homogenization.cli import calibrate  # noqa: E402
from warp_hcell.core.cli import run_main  # noqa: E402

BASE = RESULTS / "calibration_dobrany_product_50_100_mv_n0_ms_cs05_kn08_15x4s.json"


def command(record: dict, out: Path, steps: int, workers: int, start: dict[str, float] | None = None,
            spread: float = 0.0, fit_spread: bool = False) -> list[str]:
    """The base fit's ``hmodel calibrate`` arguments with its output, steps and start replaced (start: ``start``, else
    its mean; alpha0 dropped), alpha0_spread fixed at ``spread`` [deg] or calibrated from it (``fit_spread``)."""
    argv = shlex.split(record["command"])[3:]
    keep, skip, last = [], False, None
    for a in argv:
        if skip:
            skip = False
            continue
        if a in ("--out", "--steps", "--start-point", "--workers"):
            skip = True
            continue
        if last == "--data":  # the base may have run in another checkout: this one's copies
            a = str(RUNS / "data" / Path(a).name)
        elif last == "--prior":
            a = str(RUNS / Path(a).name)
        elif last == "--params" and fit_spread:
            a = a + "," + SPREAD
        keep.append(a)
        last = a
    mean = {k: v for k, v in (start or record["mean"]["values"]).items() if k not in ("alpha0", SPREAD)}
    if fit_spread:
        mean[SPREAD] = spread
    point = ",".join(f"{k}={v!r}" for k, v in mean.items())
    extra = ["--walkers", str(2 * (argv[argv.index("--params") + 1].count(",") + 2))] if fit_spread else [
        "--alpha0-spread", repr(spread)]  # walkers: at least 2 x the parameters
    return keep + extra + ["--out", str(out), "--steps", str(steps), "--workers", str(workers), "--start-point", point]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spread", type=float, required=True)
    parser.add_argument("--fit-spread", action="store_true")
    parser.add_argument("--start-run", type=Path, default=None)
    parser.add_argument("--start-scales", default=None, metavar="NAME=F1,F2,...")
    parser.add_argument("--base", type=Path, default=BASE)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--tag", default=None)
    parser.add_argument("--rules", default="15x4s,35x12s")
    parser.add_argument("--evaluate-only", action="store_true")
    parser.add_argument("--result-tag", default="")
    args = parser.parse_args(argv)
    tag = args.tag or f"{'fit' if args.fit_spread else ''}s{args.spread:g}_15x4s"
    record = json.loads(args.base.read_text())
    split = record["split"].replace("+", "_")
    out = RUNS / f"{split}_families_{tag}"
    lines: list[str] = []

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    start = post_mod.read_posterior(args.start_run).mean if args.start_run else None
    flags = command(record, out, args.steps, args.workers, start, args.spread, args.fit_spread)
    flags += ["--start-scales", args.start_scales] if args.start_scales else []
    prior = Path(flags[flags.index("--prior") + 1])
    if not prior.is_file():  # the base's prior as calibration_dobrany_product.py writes it (--fit-mobilisation[-void])
        prior.parent.mkdir(parents=True, exist_ok=True)
        extra = MOBILISATION_VOID_PRIOR if prior.stem.endswith("mobilisation_void") else MOBILISATION_PRIOR
        prior.write_text(json.dumps({**PRIOR, **extra}, indent=1))
    say("hmodel calibrate " + shlex.join(flags))
    seconds = None
    if not args.evaluate_only:
        started = time.perf_counter()
        assert run_main(calibrate.main, flags + ["--overwrite", "-q"]) == 0
        seconds = time.perf_counter() - started
    post = post_mod.read_posterior(out)
    run = json.loads((out / "run.json").read_text())
    say(f"wall {seconds} s; chi-square at the least-squares optimum {run['start'].get('chi_square')}; "
        "forward: " + json.dumps({k: run["forward_model"].get(k)
                                  for k in ("fallbacks", "renewal_clips", "interlocking_clips", "failed")}))
    mean = {name: np.array([value]) for name, value in post.mean.items()}
    say("mean: " + json.dumps({k: float(v[0]) for k, v in mean.items()}))
    rows, curves = [], {}
    fitted = {Path(flags[i + 1]).name for i, a in enumerate(flags) if a == "--data"}
    for rule in args.rules.split(","):
        order, rest = rule.split("x")
        settings = replace(post.forward, lebedev_order=int(order), n_spins=int(rest[:-1]), staggered_spins=True)
        for name, test in dobrany_tests().items():
            with np.errstate(all="ignore"):
                c = forward.simulate(test, mean, settings)
            low, high = plateau(test.eps1, c.q[0])
            row = {"rule": rule, "test": name, **shape(test, c.q[0], c.eps_v[0]),
                   "forward_fallbacks": int(c.n_fallback[0]), "plateau": [low, high],
                   "renewal_clips": int(c.n_renewal_clip[0])}
            rows.append(row)
            if rule == args.rules.split(",")[-1]:  # the figure's curves (``splits_figure``'s format)
                curves[name] = {"eps1": test.eps1, "q": c.q[0], "eps_v": c.eps_v[0], "q_data": test.observed["q"],
                                "eps_v_data": test.observed["eps_v"]}
            say(f"{rule} {name}: {text(row)}, plateau {100 * low:.2f}-{100 * high:.2f} %, renewal clips "
                f"{row['renewal_clips']}")
    stem = RESULTS / f"fit_dobrany_density_families_{split}_{tag}{'_' + args.result_tag if args.result_tag else ''}"
    stem.with_suffix(".json").write_text(json.dumps({"spread": post.mean.get(SPREAD, args.spread), "base": str(args.base),
                                                     "command": flags, "wall_seconds": seconds,
                                                     "start": run.get("start"), "mean": post.mean, "rows": rows},
                                                    indent=1, default=str))
    stem.with_suffix(".txt").write_text("\n".join(lines) + "\n")
    order, rest = args.rules.split(",")[-1].split("x")
    figure = {"split": record["split"], "command": f"--order {order} --spins {rest[:-1]} --staggered-spins",
              "mean": {"curves": curves, "tests": {name: {"role": "fitted" if name in fitted else "predicted"}
                                                   for name in curves}}}
    Path(f"{stem}_figure.json").write_text(json.dumps(figure, default=lambda a: np.asarray(a).tolist()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
