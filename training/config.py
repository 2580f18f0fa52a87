"""The settings of a training (``TrainConfig``: the single home of their defaults); the flags of
``python -m training.train`` that set them are that command's (``training.train.build_parser``).

Light on purpose: it imports neither torch nor Warp, so that the commands that read these
defaults (``hmodel train``, ``hmodel learn``) answer --help at once; the training itself is
``training.fitting``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass

DEFAULT_HIDDEN: tuple[int, ...] = (40, 40)
"""Hidden layer widths of the recommended model (the narrowest tried that meets every target of
the H-cell acceptance table, `docs/ann.md`; its inference is no slower than the analytical cell)."""


HYBRID_EPOCHS = 30
"""Maximum epochs [-] of the network of a hybrid surrogate (the network followed by exact
equilibrium corrections): where ``hmodel train`` and ``hmodel learn`` certify such a surrogate
and no --epochs is given (``training.train.for_hybrid``). The corrections, not the network's accuracy, decide its
error against the DEM (docs/ann.md, "Equilibrium corrections"; the measured validation curves and
pipeline times: docs/certificate.md, "The default pipeline of a 3D cell with fine grains")."""
HYBRID_PATIENCE = 10
"""Epochs without validation improvement before early stopping [-] of such a network (``training.train.for_hybrid``)."""


@dataclass(frozen=True)
class TrainConfig:
    """Training hyperparameters and split settings (the single home of their defaults)."""

    hidden: tuple[int, ...] = DEFAULT_HIDDEN
    """Hidden layer widths [-]."""
    load_features: bool = False
    """Give the network the load fraction f_n / max f_n of every active pair (``training.network``)."""
    sliding_weight: float = 1.0
    """Loss weight [-] of the training samples in which a contact slides (f_s = +-mu f_n) while
    another carries less than ``training.fitting.LIGHT_FRACTION`` of the cell's largest normal force
    (``training.fitting.sliding_light``);
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
    round_share: float = 0.0
    """Fraction [-] of the training and validation loss carried by the samples of active-learning
    rounds (``source_round`` > 0), whose weight is set so (``training.fitting.round_weights``);
    0: every sample weighs 1."""
    init_from: str | None = None
    """Model (.pt) whose weights start the training (warm start), None: random weights
    (``training.fitting.warm_start``). Also splits the database by round (``split_by_path(by_round=True)``)."""

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "lr_patience", "patience", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= 1")
        if not (math.isfinite(self.sliding_weight) and self.sliding_weight > 0.0):
            raise ValueError(f"sliding_weight = {self.sliding_weight:g} must be finite and > 0")
        if not 0.0 <= self.round_share < 1.0:
            raise ValueError(f"round_share = {self.round_share:g} must lie in [0, 1)")
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


def config_record(config: TrainConfig) -> dict:
    """``config`` as the model's JSON stores it (``"config"``: tuples as lists)."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(config).items()}
