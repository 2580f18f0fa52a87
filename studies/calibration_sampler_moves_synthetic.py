"""--moves stretch against de on a known truth (docs/studies/calibration_sampler_moves.md).

    python studies/calibration_sampler_moves_synthetic.py --data-seed 20 --seeds 4 --steps 60 --moves de,stretch

The data of tests/test_calibration_moves.py: two biaxial tests (undrained 50 kN/m, q and p; drained 30 kN/m, q and
eps_v; 20 points to 2 %) made by the calibration's own forward model (12 orientations, default increments) at
phi_g 22 deg, alpha0 60 deg with 2 % noise (numpy generator seeded --data-seed); calibrated (phi_g, alpha0; 8
walkers; --resolution off; least-squares start) once per moves and sampler --seed. Prints per run the posterior
means, 95 % intervals (truth in or OUT), acceptance, largest tau and stuck walkers; writes
studies/results/calibration_sampler_moves_synthetic_TAG.txt (TAG: data seed and steps).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from homogenization.calibration.synthetic import synthetic_test, write_test
from homogenization.cli import calibrate
from warp_hcell.core.cli import run_main

TRUTH = {"phi_g": 22.0, "alpha0": 60.0}
RESULTS = Path(__file__).resolve().parent / "results"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data-seed", type=int, default=20)
    parser.add_argument("--seeds", type=int, default=4, help="sampler seeds 0 .. N-1")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--moves", default="de,stretch")
    args = parser.parse_args(argv)
    base = Path(tempfile.mkdtemp())
    flags = ["--orientations", "12", "--confirm", "none", "--resolution", "off", "--params", "phi_g,alpha0",
             "--walkers", "8", "-q"]
    settings = calibrate.forward_settings(calibrate.build_parser().parse_args(["--data", "x", "--out", "x", *flags]), 2)
    rng = np.random.default_rng(args.data_seed)
    eps1 = np.linspace(0.001, 0.02, 20)
    for kind, p0, channels in (("undrained", 5e4, ("q", "p")), ("drained", 3e4, ("q", "eps_v"))):
        test, _ = synthetic_test(kind, p0, eps1, channels, TRUTH, settings, 0.02, rng)
        write_test(base / f"{kind}.csv", test)
        flags += ["--data", str(base / f"{kind}.csv")]
    lines = [f"data seed {args.data_seed}, {args.steps} steps, truth " + ", ".join(f"{k} {v}" for k, v in TRUTH.items())]
    for moves in args.moves.split(","):
        for seed in range(args.seeds):
            out = base / f"{moves}{seed}"
            assert run_main(calibrate.main, [*flags, "--moves", moves, "--seed", str(seed), "--steps", str(args.steps),
                                             "--out", str(out)]) == 0
            post = json.loads((out / "posterior.json").read_text())
            s = json.loads((out / "run.json").read_text())["sampler"]
            cells = []
            for n, v in TRUTH.items():
                lo, hi = post[n]["ci95"]
                cells.append(f"{n} {post[n]['mean']:.3f} [{lo:.3f}, {hi:.3f}] {'in' if lo <= v <= hi else 'OUT'}")
            lines.append(f"{moves} seed {seed}: " + "; ".join(cells) + f"; acceptance {s['acceptance_fraction']:.2f}, "
                         f"largest tau {max(s['autocorrelation']['tau_steps'].values()):.1f}, "
                         f"stuck {s['stuck_walkers_left_out']}")
            print(lines[-1], flush=True)
    shutil.rmtree(base)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"calibration_sampler_moves_synthetic_seed{args.data_seed}_{args.steps}steps.txt").write_text(
        "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
