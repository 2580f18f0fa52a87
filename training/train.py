"""python -m training.train --data db.h5 --out model.pt: train the generic meso-ANN on a learning database.

The command of ``training.fitting`` (the library: ``fit``, ``train_and_save``): its flags
(``build_parser``, ``config_of``: every default from ``training.config.TrainConfig``), the epochs'
progress bar (``EpochBar``) and the summary lines. It writes ``model.pt``, ``model.json``,
``model_learning_curve.png`` and the out-of-distribution index, and leaves the model
uncertified (``hmodel train`` certifies). Bad input is one line on stderr and exit code 2,
checked before training starts. The only module of ``training`` that imports the command
helpers ``warp_hcell.core.cli``; light (torch is imported when the command runs), so that
``hmodel train`` and ``hmodel learn`` build their parsers from it at once.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any, Sequence

from training.config import HYBRID_EPOCHS, HYBRID_PATIENCE, hidden_widths, TrainConfig
from warp_hcell.core.cli import (command_prog, common_parser, DefaultsHelpFormatter, Parser, progress_bar, quiet_warp,
                                 run_main, say, set_verbosity)

DESCRIPTION = "python -m training.train --data db.h5 --out model.pt: train the generic meso-ANN on a learning database."
"""The first line of the help of ``python -m training.train``."""


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {kind.__name__}") from None
        if not value > 0 or not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} must be > 0")
        return value
    return parse


def _fraction(text: str) -> float:
    """argparse type of --round-share: a number in [0, 1)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"{text} must lie in [0, 1)")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``python -m training.train`` parser; defaults come from ``TrainConfig``."""
    d = TrainConfig()
    p = Parser(prog=command_prog("training.train"), description=DESCRIPTION, parents=[common_parser()],
               formatter_class=DefaultsHelpFormatter)
    p.set_defaults(seed=d.seed, device=d.device)
    p.add_argument("--data", type=Path, required=True, help="generic learning database (HDF5, docs/database_format.md)")
    p.add_argument("--out", type=Path, required=True, help="state_dict file; metadata goes to the same stem .json")
    p.add_argument("--epochs", type=_positive(int), default=None,
                   help=f"maximum epochs (None: {d.epochs}; {HYBRID_EPOCHS} where hmodel train certifies a hybrid)")
    p.add_argument("--batch-size", type=_positive(int), default=d.batch_size, help="samples per Adam step")
    p.add_argument("--lr", type=_positive(float), default=d.lr, help="initial Adam learning rate")
    p.add_argument("--patience", type=_positive(int), default=None,
                   help=f"early-stopping patience [epochs] (None: {d.patience}; {HYBRID_PATIENCE} where hmodel train "
                        f"certifies a hybrid)")
    p.add_argument("--hidden", type=hidden_widths, default=",".join(map(str, d.hidden)), help="hidden layer widths, comma separated")
    p.add_argument("--load-features", action="store_true",
                   help="give the network the load fraction f_n / max f_n of every active pair")
    p.add_argument("--sliding-weight", type=_positive(float), default=d.sliding_weight,
                   help="loss weight of samples with a sliding contact beside a lightly loaded one")
    p.add_argument("--round-share", type=_fraction, default=d.round_share,
                   help="fraction of the loss carried by the samples of active-learning rounds (0: every sample weighs 1)")
    p.add_argument("--threads", type=_positive(int), default=d.threads, help="torch CPU threads")
    p.add_argument("--no-rollout", action="store_true", help="skip the rollout error along held-out DEM paths")
    p.add_argument("--init-from", type=Path, default=None,
                   help="warm start: begin from this model's weights (same architecture; the database split by round)")
    return p


def for_hybrid(args: argparse.Namespace) -> None:
    """Set --epochs and --patience of parsed ``build_parser`` flags that were not given to those of
    the network of a hybrid surrogate (``HYBRID_EPOCHS``, ``HYBRID_PATIENCE``)."""
    if args.epochs is None:
        args.epochs = HYBRID_EPOCHS
    if args.patience is None:
        args.patience = HYBRID_PATIENCE


def config_of(args: argparse.Namespace) -> TrainConfig:
    """The ``TrainConfig`` of parsed ``build_parser`` flags (--epochs and --patience not given:
    ``TrainConfig``'s)."""
    d = TrainConfig()
    return TrainConfig(hidden=args.hidden, load_features=args.load_features, sliding_weight=args.sliding_weight,
                       round_share=args.round_share,
                       epochs=d.epochs if args.epochs is None else args.epochs, batch_size=args.batch_size, lr=args.lr,
                       patience=d.patience if args.patience is None else args.patience,
                       seed=args.seed, threads=args.threads, device=args.device, rollout=not args.no_rollout,
                       init_from=None if args.init_from is None else str(args.init_from))


class EpochBar:
    """The progress callback (``training.fitting.Progress``) that draws a training's epochs as a
    bar: a new bar where epoch 1 is reported (one per training, several in a learning loop),
    closed after the last epoch."""

    def __init__(self) -> None:
        self.bar: Any = None

    def __call__(self, epoch: Any) -> None:
        if epoch.epoch == 1 or self.bar is None:
            self.close()
            self.bar = progress_bar(total=epoch.epochs, desc="training", unit="epoch")
        self.bar.update(1)
        self.bar.set_postfix(train=f"{epoch.train_loss:.2e}", val=f"{epoch.val_loss:.2e}", lr=f"{epoch.lr:.1e}",
                             refresh=False)
        if epoch.last:
            self.close()

    def close(self) -> None:
        """Close the bar drawn (if any)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = build_parser().parse_args(argv)
    set_verbosity(args)
    from training.fitting import train_and_save  # noqa: PLC0415 (torch: only when the command runs)

    if not args.verbose and not args.no_rollout:
        quiet_warp()  # the rollout runs the DEM on the cpu
    train_and_save(args.data, args.out, config_of(args), overwrite=args.overwrite, progress=EpochBar(), log=say,
                   command="python -m training.train " + " ".join(sys.argv[1:] if argv is None else argv))
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    """``main`` with user errors (bad data, bad model file, busy or unwritable output) as one
    line and exit code 2, Ctrl-C as one line and exit code 130."""
    return run_main(main, argv)


if __name__ == "__main__":
    sys.exit(run())
