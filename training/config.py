"""The settings of a training (``TrainConfig``: the single home of their defaults) and the flags
of ``python -m training.train`` that set them (``build_parser``, ``config_of``).

Light on purpose: it imports neither torch nor Warp, so that the commands that read these
defaults (``hmodel train``, ``hmodel learn``) answer --help at once; the training itself is
``training.train``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from warp_hcell.core.cli import command_prog, common_parser, DefaultsHelpFormatter, Parser

DESCRIPTION = "python -m training.train --data db.h5 --out model.pt: train the generic meso-ANN on a learning database."
"""The first line of the help of ``python -m training.train``."""
DEFAULT_HIDDEN: tuple[int, ...] = (40, 40)
"""Hidden layer widths of the recommended model (the narrowest tried that meets every target of
the H-cell acceptance table, `docs/ann.md`; its inference is no slower than the analytical cell)."""


HYBRID_EPOCHS = 30
"""Maximum epochs [-] of the network of a hybrid surrogate (the network followed by exact
equilibrium corrections): where ``hmodel train`` and ``hmodel learn`` certify such a surrogate
and no --epochs is given (``for_hybrid``). The corrections, not the network's accuracy, decide its
error against the DEM (docs/ann.md, "Equilibrium corrections"; the measured validation curves and
pipeline times: docs/certificate.md, "The default pipeline of a 3D cell with fine grains")."""
HYBRID_PATIENCE = 10
"""Epochs without validation improvement before early stopping [-] of such a network (``for_hybrid``)."""


@dataclass(frozen=True)
class TrainConfig:
    """Training hyperparameters and split settings (the single home of their defaults)."""

    hidden: tuple[int, ...] = DEFAULT_HIDDEN
    """Hidden layer widths [-]."""
    load_features: bool = False
    """Give the network the load fraction f_n / max f_n of every active pair (``training.network``)."""
    sliding_weight: float = 1.0
    """Loss weight [-] of the training samples in which a contact slides (f_s = +-mu f_n) while
    another carries less than ``training.train.LIGHT_FRACTION`` of the cell's largest normal force
    (``training.train.sliding_light``);
    the other samples and the validation loss have weight 1."""
    epochs: int = 300
    """Maximum number of epochs [-]."""
    batch_size: int = 256
    """Samples per Adam step [-]."""
    lr: float = 2e-3
    """Initial Adam learning rate [-]."""
    lr_patience: int = 8
    """Epochs without validation improvement before the learning rate is halved [-]."""
    min_lr: float = 1e-5
    """Learning rate below which training stops [-]."""
    patience: int = 25
    """Epochs without validation improvement before early stopping [-]."""
    val_fraction: float = 0.2
    """Fraction of the non-test paths used for validation [-]."""
    test_fraction: float = 0.1
    """Fraction of the paths held out for the test set [-]."""
    seed: int = 0
    """Seed of the split, the initial weights and the batch order."""
    threads: int = 1
    """torch CPU threads used for training [-] (on a shared 2-core machine two threads ran
    30 times slower than one: OpenMP threads spin while the other core is busy)."""
    device: str = "cpu"
    """torch device of the training."""
    rollout: bool = True
    """Measure the rollout error along held-out DEM paths after training."""
    init_from: str | None = None
    """Model (.pt) whose weights start the training (warm start), None: random weights
    (``warm_start``). Also splits the database by round (``split_by_path(by_round=True)``)."""

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "lr_patience", "patience", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= 1")
        if not (math.isfinite(self.sliding_weight) and self.sliding_weight > 0.0):
            raise ValueError(f"sliding_weight = {self.sliding_weight:g} must be finite and > 0")
        if not (math.isfinite(self.lr) and self.lr > 0.0):
            raise ValueError(f"lr = {self.lr:g} must be finite and > 0")
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden = {list(self.hidden)} must be a non-empty list of widths >= 1")


def hidden_widths(text: str) -> tuple[int, ...]:
    """argparse type of --hidden: comma-separated widths >= 1, e.g. "40,40" -> (40, 40)."""
    try:
        widths = tuple(int(w) for w in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of integers") from None
    if not widths or min(widths) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: widths must be >= 1")
    return widths


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
                       epochs=d.epochs if args.epochs is None else args.epochs, batch_size=args.batch_size, lr=args.lr,
                       patience=d.patience if args.patience is None else args.patience,
                       seed=args.seed, threads=args.threads, device=args.device, rollout=not args.no_rollout,
                       init_from=None if args.init_from is None else str(args.init_from))


def config_record(config: TrainConfig) -> dict:
    """``config`` as the model's JSON stores it (``"config"``: tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(config).items()}
