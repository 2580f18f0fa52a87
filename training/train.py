"""python -m training.train --data db.h5 --out model.pt: train the meso-ANN on a learning database.

Contract:

- ``TrainConfig`` holds every training default (the CLI reads them from it).
- ``fit(db, config) -> FitResult`` splits ``db`` by path, fits the normalisation on the
  training split, and minimises the MSE of the z-scored rate targets with Adam (learning
  rate halved on validation plateaus), early stopping on the validation loss and restoring
  the best epoch. Same seed and thread count -> bit-identical network.
- ``evaluate(net, db, index)`` gives R^2 per output, on the increments and on the
  post-increment values (physical units: alpha in deg, forces in N).
- The CLI writes ``model.pt`` (state_dict), ``model.json`` (metadata: architecture,
  normalisation, contact law, radius, training-data hash, split, metrics, configuration,
  versions) and ``model_learning_curve.png``, and prints R^2 per output on the validation
  and test sets. Bad input (missing or corrupt database, existing output without
  ``--overwrite``) is one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import platform
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, RandomSampler, TensorDataset
from tqdm import tqdm

from training.checkpoint import save_checkpoint
from training.dataset import (
    Database,
    DataError,
    Normalisation,
    Split,
    fit_normalisation,
    load_database,
    split_by_path,
    tensors,
)
from training.network import DEFAULT_HIDDEN, CellNet
from warp_hcell.database import OUTPUT_FEATURES
from warp_hcell.cli import check_output_path, device_name, output_lock, run_main
from warp_hcell.provenance import git_revision


@dataclass(frozen=True)
class TrainConfig:
    """Training hyperparameters and split settings (the single home of their defaults)."""

    hidden: tuple[int, ...] = DEFAULT_HIDDEN
    """Hidden layer widths [-]."""
    epochs: int = 400
    """Maximum number of epochs [-]."""
    batch_size: int = 512
    """Samples per Adam step [-]."""
    lr: float = 3e-3
    """Initial Adam learning rate [-]."""
    lr_patience: int = 8
    """Epochs without validation improvement before the learning rate is halved [-]."""
    min_lr: float = 1e-5
    """Learning rate below which training stops [-]."""
    patience: int = 30
    """Epochs without validation improvement before early stopping [-]."""
    val_fraction: float = 0.2
    """Fraction of the non-test paths used for validation [-]."""
    test_path_fraction: float = 0.1
    """Fraction of paths (outside held-out alpha0 values) held out for the test set [-]."""
    n_test_alpha0: int = 1
    """Number of distinct alpha0 values whose paths are all held out for the test set [-]."""
    seed: int = 0
    """Seed of the split, the initial weights and the batch order."""
    threads: int = 2
    """torch CPU threads used for training [-]."""
    device: str = "cpu"
    """torch device of the training."""

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "lr_patience", "patience", "threads"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} = {getattr(self, name)} must be >= 1")
        if not (math.isfinite(self.lr) and self.lr > 0.0):
            raise ValueError(f"lr = {self.lr:g} must be finite and > 0")
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden = {list(self.hidden)} must be a non-empty list of widths >= 1")


@dataclass(frozen=True)
class FitResult:
    """Outcome of ``fit``.

    Attributes:
        net: the network at its best validation epoch (eval mode, on the CPU).
        history: per-epoch ``epoch``, ``train_loss``, ``val_loss`` (MSE of z-scored
            rates [-]) and ``lr``; ``best_epoch``; ``seconds`` of training.
        split: the sample split used; normalisation: its training statistics.
    """

    net: CellNet
    history: dict = field(repr=False)
    split: Split
    normalisation: Normalisation


def _mse(net: CellNet, x: torch.Tensor, y: torch.Tensor, chunk: int = 65536) -> float:
    with torch.no_grad():
        total = sum(float(((net(x[i:i + chunk]) - y[i:i + chunk]) ** 2).sum()) for i in range(0, x.shape[0], chunk))
    return total / y.numel()


def fit(db: Database, config: TrainConfig = TrainConfig(), *, progress: bool = False) -> FitResult:
    """Train a ``CellNet`` on ``db`` (see module docstring); deterministic for a given seed.

    Sets torch's process-wide thread count (``config.threads``) and deterministic mode.
    """
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(config.seed)
    split = split_by_path(db, val_fraction=config.val_fraction, test_path_fraction=config.test_path_fraction,
                          n_test_alpha0=config.n_test_alpha0, seed=config.seed)
    norm = fit_normalisation(db, split.train)
    device = torch.device(config.device)
    x_train, y_train = (t.to(device) for t in tensors(db, split.train, norm))
    x_val, y_val = (t.to(device) for t in tensors(db, split.val, norm))
    net = CellNet(config.hidden, kn=db.kn, diameter=db.diameter, mu=db.mu)
    net.set_normalisation(norm.feature_mean, norm.feature_std, norm.rate_mean, norm.rate_std)
    net.to(device)
    train_set = TensorDataset(x_train, y_train)
    sampler = BatchSampler(RandomSampler(train_set, generator=torch.Generator().manual_seed(config.seed)),
                           batch_size=config.batch_size, drop_last=False)
    loader = DataLoader(train_set, sampler=sampler, batch_size=None)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr)
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimiser, factor=0.5, patience=config.lr_patience)
    history: dict = {"epoch": [], "train_loss": [], "val_loss": [], "lr": []}
    best_loss, best_state, best_epoch = math.inf, copy.deepcopy(net.state_dict()), 0
    start = time.perf_counter()
    bar = tqdm(range(1, config.epochs + 1), desc="training", unit="epoch", disable=not progress)
    for epoch in bar:
        net.train()
        running = 0.0
        for x, y in loader:
            optimiser.zero_grad(set_to_none=True)
            loss = torch.mean((net(x) - y) ** 2)
            loss.backward()
            optimiser.step()
            running += loss.item() * x.shape[0]
        net.eval()
        val_loss = _mse(net, x_val, y_val)
        lr = optimiser.param_groups[0]["lr"]
        for key, value in zip(history, (epoch, running / x_train.shape[0], val_loss, lr)):
            history[key].append(value)
        if val_loss < best_loss:
            best_loss, best_state, best_epoch = val_loss, copy.deepcopy(net.state_dict()), epoch
        bar.set_postfix(train=f"{history['train_loss'][-1]:.2e}", val=f"{val_loss:.2e}", lr=f"{lr:.1e}")
        scheduler.step(val_loss)
        if epoch - best_epoch >= config.patience or optimiser.param_groups[0]["lr"] < config.min_lr:
            break
    net.load_state_dict(best_state)
    history["best_epoch"] = best_epoch
    history["seconds"] = time.perf_counter() - start
    return FitResult(net.cpu().eval(), history, split, norm)


def r2(prediction: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Coefficient of determination per column, shape (n_columns,)."""
    residual = ((prediction - truth) ** 2).sum(axis=0)
    total = ((truth - truth.mean(axis=0)) ** 2).sum(axis=0)
    return 1.0 - residual / np.where(total > 0, total, np.nan)


def evaluate(net: CellNet, db: Database, index: np.ndarray) -> dict[str, dict[str, float]]:
    """R^2 per output on samples ``index``: ``{"increment": {...}, "value": {...}}``.

    Increments are post minus pre ``alpha_deg, N1, N2, T1`` [deg, N]; values are the
    post-increment state. Keys of the inner dicts: ``d_alpha, dN1, dN2, dT1`` and
    ``alpha, N1, N2, T1``.
    """
    inputs = torch.from_numpy(db.inputs[index])
    predicted = net.predict(inputs).numpy()
    truth = db.outputs[index]
    pre = db.inputs[index][:, 2:6]
    names = [name.removesuffix("_deg") for name in OUTPUT_FEATURES]
    return {
        "increment": dict(zip((f"d{n}" if n != "alpha" else "d_alpha" for n in names), map(float, r2(predicted - pre, truth - pre)))),
        "value": dict(zip(names, map(float, r2(predicted, truth)))),
    }


def _plot_learning_curve(path: Path, history: dict) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
    ax.semilogy(history["epoch"], history["train_loss"], label="training")
    ax.semilogy(history["epoch"], history["val_loss"], label="validation")
    ax.axvline(history["best_epoch"], color="0.6", ls=":", label=f"best epoch {history['best_epoch']}")
    ax.set_xlabel("epoch [-]")
    ax.set_ylabel("MSE of z-scored rates [-]")
    ax.legend()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _hidden(text: str) -> tuple[int, ...]:
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
    p = argparse.ArgumentParser(prog="python -m training.train", description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="learning database (HDF5, docs/database_format.md)")
    p.add_argument("--out", type=Path, required=True, help="state_dict file; metadata goes to the same stem .json")
    p.add_argument("--epochs", type=_positive(int), default=d.epochs, help="maximum epochs")
    p.add_argument("--batch-size", type=_positive(int), default=d.batch_size, help="samples per Adam step")
    p.add_argument("--lr", type=_positive(float), default=d.lr, help="initial Adam learning rate")
    p.add_argument("--patience", type=_positive(int), default=d.patience, help="early-stopping patience [epochs]")
    p.add_argument("--hidden", type=_hidden, default=",".join(map(str, d.hidden)), help="hidden layer widths, comma separated")
    p.add_argument("--n-test-alpha0", type=int, default=d.n_test_alpha0, help="alpha0 values held out for the test set")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the split, weights and batch order")
    p.add_argument("--threads", type=_positive(int), default=d.threads, help="torch CPU threads")
    p.add_argument("--device", type=device_name, default=d.device, help="torch device (cpu, cuda)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing model instead of refusing")
    return p


def _format_r2(metrics: dict[str, dict[str, float]]) -> str:
    digits = {"increment": 6, "value": 10}
    return "  ".join(f"{k}={v:.{digits[group]}f}" for group in digits for k, v in metrics[group].items())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    args = build_parser().parse_args(argv)
    out: Path = args.out
    curve = out.with_name(f"{out.stem}_learning_curve.png")
    if not args.overwrite and any(p.exists() for p in (out, out.with_suffix(".json"), curve)):
        raise DataError(f"{out} (or its .json/.png) exists; pass --overwrite to replace it")
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; give a file name")
    check_output_path(out, overwrite=True)  # writable, checked before training
    with output_lock(out):
        return _train(args, out, curve, argv)


def _train(args: argparse.Namespace, out: Path, curve: Path, argv: Sequence[str] | None) -> int:
    """Train, evaluate and write the model of ``main`` (holding the output lock)."""
    config = TrainConfig(hidden=args.hidden, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                         patience=args.patience, n_test_alpha0=args.n_test_alpha0, seed=args.seed,
                         threads=args.threads, device=args.device)
    db = load_database(args.data)
    result = fit(db, config, progress=True)
    metrics = {name: evaluate(result.net, db, getattr(result.split, name)) for name in ("train", "val", "test")}
    split = result.split
    metadata = {
        "contact_law": {"kn": db.kn, "kt_over_kn": db.kt_over_kn, "phi_g_deg": db.phi_g_deg},
        "radius": db.radius,
        "target": "rate = (post - pre) / |d_eps| of alpha [rad], N1, N2, T1 [kn D]; increment = |d_eps| * rate",
        "training_data": {"path": str(args.data), "sha256": db.sha256, "n_stored": db.n_stored,
                          "n_selected": db.n_samples, "n_train": int(split.train.size), "n_val": int(split.val.size),
                          "n_test": int(split.test.size), "test_alpha0_deg": list(split.test_alpha0_deg),
                          "n_removed_jumps": db.n_jumps,
                          "selection": "valid & warp_hcell.clean rules & |d_eps| > 0 & |rate| <= RATE_LIMIT"},
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(config).items()},
        "metrics_r2": metrics,
        "history": {"best_epoch": result.history["best_epoch"], "seconds": result.history["seconds"],
                    "epochs_run": len(result.history["epoch"]),
                    "best_val_loss": min(result.history["val_loss"])},
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
                     "git_revision": git_revision()},
        "command": "python -m training.train " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    save_checkpoint(out, result.net, metadata)
    _plot_learning_curve(curve, result.history)
    print(f"trained {len(result.history['epoch'])} epochs in {result.history['seconds']:.1f} s "
          f"(best epoch {result.history['best_epoch']}); samples train/val/test = "
          f"{split.train.size}/{split.val.size}/{split.test.size}; test alpha0 held out = {list(split.test_alpha0_deg)} deg")
    for name in ("val", "test"):
        print(f"R^2 {name:>4}: {_format_r2(metrics[name])}")
    print(f"wrote {out}, {out.with_suffix('.json')}, {curve}")
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    """``main`` with user errors (bad data, bad model file, busy or unwritable output) as one
    line and exit code 2, Ctrl-C as one line and exit code 130."""
    return run_main(main, argv)


if __name__ == "__main__":
    sys.exit(run())
