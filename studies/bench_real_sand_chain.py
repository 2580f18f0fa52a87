"""python studies/bench_real_sand_chain.py --split 50+200 --work runs/dobrany_chain [--run] [--steps 80]

``hmodel calibrate --critical-state`` on two drained triaxial tests of Dobrany sand, each at its specimen's
void ratio (``# void_ratio = E`` from ``specimens.json``), then the third test predicted at the posterior mean.
Writes the two data files with their void ratios and the prior (``PRIOR``: a box about the least-squares
optima of ``bench_real_sand_critical_state.py --void-ratio``) under WORK/data, and prints the calibrate
command (``COMMAND``: 16 walkers, start at the best prior draws, --model-error 0.17, the study's forward
settings, --resolution off, --confirm none); ``--run`` runs it into WORK/calibration. Then reads
WORK/calibration (its posterior.json and run.json, ``calibration.posterior.read_posterior``: the rule at the
posterior mean) and prints the sampler's diagnostics (steps, acceptance, autocorrelation times, steps needed)
and, at the posterior mean, per test RMS abs(dq) / q_peak, RMS d eps_v, q_peak and its strain (largest q
within the first 10 % of strain too), model against data. Result: studies/results/real_sand_chain_SPLIT.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real_sand import DATA, SPLITS, print_prediction_table  # noqa: E402
from bench_real_sand_spread import metrics  # noqa: E402

from homogenization.calibration.data import read_test  # noqa: E402
from homogenization.calibration.forward import simulate  # noqa: E402
from homogenization.calibration.posterior import read_posterior  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
PARAMS = "phi_g,kn,kt_over_kn,e_min,e_max,alpha_c,renewal_rate"
PRIOR = {"phi_g": [35, 40], "kn": {"low": 1.5e7, "high": 4e7, "log": True}, "kt_over_kn": [1.1, 1.5],
         "e_min": [0.43, 0.47], "e_max": [0.70, 0.76], "alpha_c": [51, 55],
         "renewal_rate": {"low": 8, "high": 25, "log": True}}
"""A box about the two splits' least-squares optima (docs/studies/calibration_dobrany_critical_state.md)."""
COMMAND = ("--critical-state", "--params", PARAMS, "--walkers", "16", "--start", "prior", "--model-error", "0.17",
           "--increment", "2e-3", "--iso-increment", "1e-3", "--stress-rtol", "1e-5", "--resolution", "off",
           "--confirm", "none")
"""The calibrate flags besides --data, --prior, --steps and --out. --model-error 0.17: the optima's misfit,
RMS 8.4 sigma at 2 % noise, is a model error of about 0.02 sqrt(8.4^2 - 1)."""


def void_ratio_file(name: str, folder: Path) -> Path:
    """The data file ``name`` with its specimen's void ratio at the start of shear in its header."""
    specimens = json.loads((DATA / "specimens.json").read_text())["tests"]
    e = next(t for t in specimens if t.get("file") == name)["void_ratio_start_of_shear"]
    lines = (DATA / name).read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("# p0")) + 1
    path = folder / name
    path.write_text("\n".join(lines[:at] + [f"# void_ratio = {e:.6f}"] + lines[at:]) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", choices=tuple(SPLITS), default="50+200")
    parser.add_argument("--work", type=Path, default=Path("runs/dobrany_chain"))
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--run", action="store_true", help="run the calibration (else read WORK/calibration)")
    args = parser.parse_args(argv)
    fitted, predicted = SPLITS[args.split]
    data = args.work / "data"
    data.mkdir(parents=True, exist_ok=True)
    files = [void_ratio_file(name, data) for name in fitted]
    prior = data / "prior.json"
    prior.write_text(json.dumps(PRIOR))
    out = args.work / "calibration"
    command = ["calibrate", *[a for f in files for a in ("--data", str(f))], *COMMAND, "--prior", str(prior),
               "--steps", str(args.steps), "--out", str(out)]
    print("$ hmodel " + " ".join(command), flush=True)
    if args.run and subprocess.run([sys.executable, "-m", "homogenization.hmodel", *command]).returncode != 0:
        return 1
    run = json.loads((out / "run.json").read_text())
    sampler = run["sampler"]
    post = read_posterior(out)
    print(f"sampler: {sampler['walkers']} walkers x {sampler['steps']} steps, acceptance "
          f"{sampler['acceptance_fraction']:.3f}, {sampler['seconds_this_run']:.0f} s this run; autocorrelation: "
          + json.dumps(sampler["autocorrelation"]))
    print("posterior mean: " + ", ".join(f"{k} {v:.4g}" for k, v in post.mean.items())
          + f"; rule alpha_c {post.forward.critical_state.alpha_c_deg:.3f} deg, rate {post.forward.critical_state.rate:.3g}")
    rows, curves = {}, {}
    for name in sorted((*fitted, predicted), key=lambda f: read_test(DATA / f).p0):
        test = read_test(void_ratio_file(name, data))
        with np.errstate(all="ignore"):
            c = simulate(test, {k: np.array([v]) for k, v in post.mean.items()}, post.forward)
        early = test.eps1 <= 0.1
        k = int(np.nanargmax(np.where(early, c.q[0], -np.inf)))
        rows[name] = {"role": "predicted" if name == predicted else "fitted", **metrics(test, c.q[0], c.eps_v[0]),
                      "q_peak_model_first_10pc": float(c.q[0, k]), "eps1_at_peak_model_first_10pc": float(test.eps1[k]),
                      "forward_fallbacks": int(c.n_fallback[0])}
        curves[name] = {"eps1": test.eps1.tolist(), "q": c.q[0].tolist(), "eps_v": c.eps_v[0].tolist()}
    print_prediction_table(rows, fallbacks=True)
    print("largest q within the first 10 % of strain: " + ", ".join(
        f"{n} {r['q_peak_model_first_10pc'] / 1e3:.0f} kPa at {100 * r['eps1_at_peak_model_first_10pc']:.1f} %"
        for n, r in rows.items()))
    RESULTS.mkdir(exist_ok=True)
    result = {"split": args.split, "command": "hmodel " + " ".join(command), "sampler": sampler,
              "posterior": run["posterior"], "rule_at_mean": post.forward.critical_state.__dict__,
              "tests": rows, "curves": curves, "load_average": list(os.getloadavg())}
    (RESULTS / f"real_sand_chain_{args.split.replace('+', '_')}.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
