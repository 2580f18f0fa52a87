"""Active learning with and without a warm start: epochs, seconds and certificate per round, side by side.

``python studies/bench_warm_start.py --out DIR [hmodel learn options]``
``python studies/bench_warm_start.py --out DIR --data DB.h5 [hmodel train options]``

Runs ``hmodel learn`` (or, with --data, ``hmodel train`` on a copy of DB.h5 in each folder,
``DIR/NAME/db.h5``, model ``DIR/NAME/ann.pt``) twice with the given options, into ``DIR/scratch`` (``--no-warm-start``:
every round retrains from random weights) and ``DIR/warm`` (``--warm-start``: from the previous
round's weights, ``training.train --init-from``), then prints per round the training epochs,
the training seconds, the round's seconds (probing, training, certifying) and the certificate's
worst figure of each, and the ratios warm / scratch of the epochs and training seconds summed
over the rounds after round 0 (round 0 is the same model in both: it is trained before any
round). With ``hmodel learn`` both runs share the database of round 0 only through the same
--seed; each folder generates its own (the generator is bit-reproducible). A folder left by an
earlier call is continued (both commands resume), so rerunning prints the same table.

Examples: docs/certificate.md, "Warm start".
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from homogenization.learning import certificate
from homogenization.cli import hmodel


def _rounds(folder: Path) -> list[dict]:
    return json.loads((folder / "ann.json").read_text())["active_learning"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the two runs (scratch/, warm/)")
    parser.add_argument("--data", type=Path, default=None, help="run hmodel train on a copy of this database")
    args, command_args = parser.parse_known_args(argv)
    runs = {}
    for name, flag in (("scratch", "--no-warm-start"), ("warm", "--warm-start")):
        folder = args.out / name
        if args.data is None:
            command = ["learn", *command_args, "--out", str(folder)]
        else:
            folder.mkdir(parents=True, exist_ok=True)
            if not (folder / "db.h5").is_file():
                shutil.copyfile(args.data, folder / "db.h5")
            command = ["train", *command_args, "--data", str(folder / "db.h5"), "--out", str(folder / "ann.pt")]
        code = hmodel.main([*command, flag, "-q"])
        if code not in (0, certificate.EXIT_FAILED, certificate.EXIT_WEAK):  # 3, 4: a certificate not passed, a result
            print(f"hmodel learn ({name}) exited {code}", file=sys.stderr)
            return code
        runs[name] = _rounds(args.out / name)
    print("round | scratch: epochs, train s, round s, worst % | warm: epochs, train s, round s, worst %")
    for k in range(max(len(r) for r in runs.values())):
        cells = []
        for name in runs:
            entry = runs[name][k] if k < len(runs[name]) else None
            cells.append("-" if entry is None else f"{entry.get('epochs', '-')}, {entry.get('train_seconds', 0):.1f}, "
                         f"{entry['seconds']:.1f}, {100 * entry['worst']:.3f}{'' if entry['passed'] else ' FAILED'}")
        print(f"{k} | {cells[0]} | {cells[1]}")
    total = {name: [sum(e.get(key, 0) for e in rounds[1:]) for key in ("epochs", "train_seconds")]
             for name, rounds in runs.items()}
    if total["scratch"][0] and total["scratch"][1]:
        print(f"rounds >= 1: epochs warm / scratch = {total['warm'][0]} / {total['scratch'][0]} = "
              f"{total['warm'][0] / total['scratch'][0]:.2f}; training seconds {total['warm'][1]:.1f} / "
              f"{total['scratch'][1]:.1f} = {total['warm'][1] / total['scratch'][1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
