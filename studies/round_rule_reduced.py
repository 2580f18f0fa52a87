"""python studies/round_rule_reduced.py [--seeds 0,1] [--rounds 3] [--samples-per-round 3000]

The active-learning rounds' rule on the reduced pipeline of the tests (a 48-sample database of the
2D H-cell, a 16-wide network of 30 epochs, the certificate's short form: one pressure, 6
orientations, 2 % axial strain, a target no model meets so that every round runs): per seed, each
round's certificate worst, whether the rule accepted it, its training seed, and the worst the kept
model has after it, beside the worst the last round's model has (what a loop that keeps every
round would ship). Printed as a table and written to studies/results/round_rule_reduced.txt.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from dem_database import build  # noqa: E402
from homogenization.learning import active  # noqa: E402
from homogenization.learning.settings import ActiveSettings, CertificateSettings  # noqa: E402
from training.config import TrainConfig  # noqa: E402
from training.fitting import train_and_save  # noqa: E402
from warp_hcell.core.cli import quiet_warp  # noqa: E402
from warp_hcell.mesostructures.hcell import h_cell  # noqa: E402

SHORT = {"pressures": (2e5,), "eps_max": 0.02, "n_orientations": 6, "rollout": False, "target": 1e-9}
CONFIG = TrainConfig(epochs=30, hidden=(16,), threads=1, rollout=False)


def one_run(seed: int, rounds: int, samples: int) -> list[str]:
    with tempfile.TemporaryDirectory() as tmp:
        db = build(Path(tmp) / "db.h5", mesostructure=h_cell(55.0), precompression=(0.0, 2e-3), n_directions=6,
                   spacing=1e-2, leg_length=0.04, threads=1)
        model = Path(tmp) / "m.pt"
        train_and_save(db, model, CONFIG)
        done, _ = active.learn(db, model, CONFIG, seed=seed, log=lambda *lines: None,
                               settings=ActiveSettings(rounds=rounds, samples_per_round=samples, stall_rounds=rounds + 1,
                                                       widen=False),
                               certify_settings=CertificateSettings(**SHORT))
    rows = []
    for k, entry in enumerate(done):
        kept = active.kept_round(done[:k + 1])
        rows.append(f"{seed:>4} {entry.round:>5} {100 * entry.worst:>11.3f} {str(entry.accepted):>8} "
                    f"{entry.train_seed:>10} {100 * kept.worst:>15.3f}")
    rows.append(f"{seed:>4}  last round's model {100 * done[-1].worst:.3f} %, kept model {100 * kept.worst:.3f} %; "
                + active.rules_line(done))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0,1", help="seeds of the rounds' probes, comma separated")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--samples-per-round", type=int, default=3000)
    args = parser.parse_args()
    quiet_warp()
    lines = [f"{'seed':>4} {'round':>5} {'worst [%]':>11} {'accepted':>8} {'train seed':>10} {'kept worst [%]':>15}"]
    for seed in (int(s) for s in args.seeds.split(",")):
        lines += one_run(seed, args.rounds, args.samples_per_round)
    text = "\n".join(lines)
    print(text)
    out = ROOT / "studies" / "results" / "round_rule_reduced.txt"
    out.write_text(text + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
