"""python -m training.ood --model M.pt --data DB.h5: write a trained model's out-of-distribution index.

The command of ``training.ood`` (which runs it as its ``__main__``): reads the model and its
database, builds the index of the split its JSON's ``config`` names (``training.ood.index_for_model``)
and writes it beside the model (``training.ood.index_path``), one line saying what it wrote.
``training.train`` writes the index at the end of training; this rebuilds it. Bad input is one
line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from warp_hcell.core.cli import run_main, say


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m training.ood`` parser."""
    parser = argparse.ArgumentParser(prog="python -m training.ood", description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="trained model (.pt, JSON beside it)")
    parser.add_argument("--data", type=Path, required=True, help="the learning database it was trained on")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = build_parser().parse_args(argv)
    from training.checkpoint import load_checkpoint  # noqa: PLC0415 (torch: only when the command runs)
    from training.dataset import load_database  # noqa: PLC0415
    from training.ood import index_for_model, index_path  # noqa: PLC0415

    net, meta = load_checkpoint(args.model)
    db = load_database(args.data)
    index = index_for_model(net, meta["config"], db)
    out = index.save(index_path(args.model))
    say(f"{index.points.shape[0]} states indexed, threshold {index.threshold:.4g} (quantile {index.quantile:g} of "
        f"held-out states) -> {out}")
    if db.sha256 != meta.get("training_data", {}).get("sha256"):
        say(f"note: {args.data} is not the database the model's JSON names (sha256 differs)")
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    """``main`` with user errors as one line and exit code 2, Ctrl-C as one line and exit code 130."""
    return run_main(main, argv)


if __name__ == "__main__":
    sys.exit(run())
