"""Training of the generic meso-ANN on a learning database (the library of ``python -m training.train``).

Contract:

- ``TrainConfig`` (``training.config``, light) holds every training default; the defaults
  give the recommended model.
- ``fit(db, config) -> FitResult`` splits ``db`` by path, fits the normalisation on the
  training split and minimises, with Adam (learning rate halved on validation plateaus,
  early stopping, best epoch restored), the mean squared error of the predicted free-DOF
  displacement relative to each sample's scale ``D (|d_eps| + |F|max / (kn D))`` and to the
  rate spread of each DOF (in the training loss, the samples that ``sliding_light`` flags
  are weighted by ``TrainConfig.sliding_weight``). Same seed and thread count -> bit-identical
  network. Each finished epoch goes to a ``progress`` callback (``Epoch``); the commands draw the bar.
- ``evaluate(net, db, index)`` gives R^2 per learned output: the free-DOF rates
  ``d x / (D |d_eps|)`` of the unperturbed samples, the free-DOF displacements d x / D of the
  perturbed ones, and the resulting increments of S_nn, S_tt (contact law applied).
- ``training.rollout.rollout_report`` gives the error along whole held-out DEM paths.
- ``train_and_save`` writes ``model.pt``, ``model.json`` (metadata: architecture, schema, contact law,
  mesostructure and its hash, training-data hash, split, metrics, rollout errors,
  configuration, versions), ``model_learning_curve.png`` and the out-of-distribution index;
  its summary lines go to a ``log`` callback.
"""

from __future__ import annotations

import copy
import math
import platform
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from training import cell_physics
from training.checkpoint import load_checkpoint, save_checkpoint
from training.dataset import (
    Database,
    DataError,
    Normalisation,
    Split,
    Tensors,
    active_pairs,
    fit_normalisation,
    load_database,
    split_by_path,
    tensors,
)
from training.config import config_record, TrainConfig
from training.network import MesoNet, pair_features
from training.ood import index_for_model, index_path
from training.rollout import rollout_report
from warp_hcell.core.files import check_output_path, output_lock
from warp_hcell.mesostructures.files import from_description
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.core.provenance import git_revision


@dataclass(frozen=True)
class FitResult:
    """Outcome of ``fit``.

    Attributes:
        net: the network at its best validation epoch (eval mode, on the CPU).
        history: per-epoch ``epoch``, ``train_loss``, ``val_loss`` and ``lr``; ``best_epoch``;
            ``seconds`` of training.
        split: the sample split used; normalisation: its training statistics.
    """

    net: MesoNet
    history: dict = field(repr=False)
    split: Split
    normalisation: Normalisation


@dataclass(frozen=True)
class Epoch:
    """One finished epoch of ``fit``, as its ``progress`` callback receives it."""

    epoch: int
    """Its number, from 1 [-]."""
    epochs: int
    """The most epochs the training may run (``TrainConfig.epochs``) [-]."""
    train_loss: float
    """Mean weighted training loss over the epoch [-]."""
    val_loss: float
    """Validation loss after it [-]."""
    lr: float
    """Adam's learning rate during it [-]."""
    last: bool
    """Whether the training stops after it (early stopping, the learning rate floor or the last epoch)."""


Progress = Callable[[Epoch], None]
"""A progress callback of ``fit``: called once per finished epoch."""


LIGHT_FRACTION = 0.15
"""Load fraction f_n / max f_n below which a closed contact counts as light in ``sliding_light`` [-]."""


def sliding_light(net: MesoNet, data: Tensors) -> torch.Tensor:
    """bool (n,): samples where an active pair slides (abs(f_s) = mu f_n to 1e-6) while another active
    pair carries a normal force above 0 and below ``LIGHT_FRACTION`` of the largest one, from the raw
    features of ``data`` (``training.network.features_and_contacts`` layout)."""
    n_active = int(net.active.sum())
    names = pair_features(net.schema.dim)
    base = 2 * net.schema.dim + 2 * net.n_free
    pair = data.features[:, base:base + len(names) * n_active].reshape(-1, n_active, len(names))
    closed = pair[..., names.index("contact")] > 0.5
    fn = torch.where(closed, torch.clamp(pair[..., names.index("overlap")], min=0.0), 0.0)
    largest = fn.amax(dim=1, keepdim=True)
    light = (fn > 0) & (fn < LIGHT_FRACTION * largest)
    sliding = closed & ((pair[..., names.index("friction_ratio")].abs() - 1.0).abs() < 1e-6)
    return sliding.any(dim=1) & light.any(dim=1)


def round_weights(source_round: np.ndarray, share: float) -> torch.Tensor:
    """float64 (n, 1) loss weights of samples from ``source_round`` (0: the generator): the
    samples of active-learning rounds (> 0) carry the fraction ``share`` of the summed weight, the
    generator's weigh 1 (all 1 where ``share`` is 0 or one kind is absent)."""
    from_rounds = source_round > 0
    n_rounds, n_generator = int(from_rounds.sum()), int((~from_rounds).sum())
    weight = np.ones(source_round.shape[0])
    if share > 0.0 and n_rounds and n_generator:
        weight[from_rounds] = share / (1.0 - share) * n_generator / n_rounds
    return torch.from_numpy(weight)[:, None]


def _loss_terms(net: MesoNet, data: Tensors, index) -> torch.Tensor:
    predicted = net.displacement_from_features(data.features[index], data.magnitude[index], data.unbalanced[index])
    return ((predicted - data.target[index]) / (data.scale[index] * net.rate_std * net.schema.diameter)) ** 2


def _mse(net: MesoNet, data: Tensors, chunk: int = 65536, weight: torch.Tensor | None = None) -> float:
    n = data.target.shape[0]
    with torch.no_grad():
        if weight is None:
            total = sum(float(_loss_terms(net, data, slice(i, i + chunk)).sum()) for i in range(0, n, chunk))
            return total / data.target.numel()
        total = sum(float((weight[i:i + chunk] * _loss_terms(net, data, slice(i, i + chunk))).sum())
                    for i in range(0, n, chunk))
    return total / float(weight.sum() * data.target.shape[1])


def fit(db: Database, config: TrainConfig = TrainConfig(), *, progress: Progress | None = None) -> FitResult:
    """Train a ``MesoNet`` on ``db`` (see module docstring); deterministic for a given seed.
    ``progress`` receives every finished epoch (``Epoch``; None: silent).

    Sets torch's process-wide thread count (``config.threads``) and deterministic mode.
    """
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(config.seed)
    split = split_by_path(db, val_fraction=config.val_fraction, test_fraction=config.test_fraction, seed=config.seed,
                          by_round=config.init_from is not None)
    active = active_pairs(db, split.train)
    train, val = (tensors(db, index, active, config.load_features) for index in (split.train, split.val))
    norm = fit_normalisation(db, train, split.train)
    net = MesoNet(db.schema, torch.from_numpy(active), config.hidden, config.load_features)
    net.set_normalisation(norm.feature_mean, norm.feature_std, norm.rate_mean, norm.rate_std)
    warm = warm_start(net, db, config.init_from) if config.init_from is not None else None
    weight = torch.where(sliding_light(net, train), config.sliding_weight, 1.0)[:, None]
    val_weight = None
    if config.round_share > 0.0:
        weight = weight * round_weights(db.source_round[split.train], config.round_share).to(weight.dtype)
        val_weight = round_weights(db.source_round[split.val], config.round_share).to(weight.dtype)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr)
    scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(optimiser, factor=0.5, patience=config.lr_patience)
    generator = torch.Generator().manual_seed(config.seed)
    history: dict = {"epoch": [], "train_loss": [], "val_loss": [], "lr": []}
    best_loss, best_state, best_epoch = math.inf, copy.deepcopy(net.state_dict()), 0
    start = time.perf_counter()
    n_train = train.target.shape[0]
    for epoch in range(1, config.epochs + 1):
        net.train()
        running = 0.0
        for batch in torch.randperm(n_train, generator=generator).split(config.batch_size):
            optimiser.zero_grad(set_to_none=True)
            loss = torch.mean(weight[batch] * _loss_terms(net, train, batch))
            loss.backward()
            optimiser.step()
            running += loss.item() * batch.numel()
        net.eval()
        val_loss = _mse(net, val, weight=val_weight)
        lr = optimiser.param_groups[0]["lr"]
        for key, value in zip(history, (epoch, running / n_train, val_loss, lr)):
            history[key].append(value)
        if val_loss < best_loss:
            best_loss, best_state, best_epoch = val_loss, copy.deepcopy(net.state_dict()), epoch
        scheduler.step(val_loss)
        stop = epoch - best_epoch >= config.patience or optimiser.param_groups[0]["lr"] < config.min_lr
        if progress is not None:
            progress(Epoch(epoch, config.epochs, history["train_loss"][-1], val_loss, lr, stop or epoch == config.epochs))
        if stop:
            break
    net.load_state_dict(best_state)
    history["best_epoch"] = best_epoch
    history["seconds"] = time.perf_counter() - start
    history["warm_start"] = warm
    return FitResult(net.eval(), history, split, norm)


def warm_start(net: MesoNet, db: Database, path: str) -> dict:
    """Start ``net`` (random weights, normalisation of its training split set) from the weights
    of model ``path``; returns ``{"from": path, "used": bool, "reason": str | None}``.

    The feature scaling is the new training split's (recomputed, as for a model trained from
    scratch: the out-of-distribution index and the backend z-score with the network's own
    statistics), and the start model's first and last layers are re-expressed in it
    (``reexpress``), so that ``net`` starts as the very function of the start model. Declined
    (``used`` False, random weights kept, ``reason`` says why) where the start model has another
    mesostructure, hidden widths, load features or active pairs, or where its split cannot be
    kept: a model trained without a warm start on a database that already held active-learning
    rounds was split in one permutation, whose validation and test paths the split by round
    (``split_by_path``) would partly train on.
    """
    previous, meta = load_checkpoint(path)
    before = db.row < int(meta["training_data"]["n_stored"])
    checks = (
        (meta["mesostructure_sha256"] == db.mesostructure_sha256, "another mesostructure"),
        (previous.hidden == net.hidden, f"hidden widths {list(previous.hidden)}, not {list(net.hidden)}"),
        (previous.load_features == net.load_features, "another load-features setting"),
        (torch.equal(previous.active, net.active), "other active pairs (the new samples touch other pairs)"),
        (meta["config"].get("init_from") is not None or not np.any(db.source_round[before] > 0),
         "its split cannot be kept (trained from scratch on a database with active-learning rounds)"),
    )
    reason = next((why for ok, why in checks if not ok), None)
    if reason is None:
        net.mlp.load_state_dict(reexpress(previous, net))
    return {"from": str(path), "used": reason is None, "reason": reason}


def reexpress(previous: MesoNet, net: MesoNet) -> dict[str, torch.Tensor]:
    """``previous.mlp``'s weights in ``net``'s normalisation (same architecture): with
    z = (x - m) / s the first layer W z_old + b = W diag(s_new / s_old) z_new + W (m_new - m_old) / s_old + b,
    and the rate rows of the last layer (rate = out * rate_std + rate_mean) are scaled by
    rate_std_old / rate_std_new and shifted by (rate_mean_old - rate_mean_new) / rate_std_new;
    the compliance rows are unscaled. Returns a state_dict for ``net.mlp``."""
    state = {k: v.detach().clone() for k, v in previous.mlp.state_dict().items()}
    linear = [name for name, module in previous.mlp.named_children() if isinstance(module, torch.nn.Linear)]
    first, last, n = linear[0], linear[-1], net.n_free
    w = state[f"{first}.weight"]
    state[f"{first}.bias"] = state[f"{first}.bias"] + w @ ((net.feature_mean - previous.feature_mean) / previous.feature_std)
    state[f"{first}.weight"] = w * (net.feature_std / previous.feature_std)[None, :]
    ratio = previous.rate_std / net.rate_std
    state[f"{last}.weight"][:n] *= ratio[:, None]
    state[f"{last}.bias"][:n] = state[f"{last}.bias"][:n] * ratio + (previous.rate_mean - net.rate_mean) / net.rate_std
    return state


def r2(prediction: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Coefficient of determination per column, shape (n_columns,); NaN for a constant column."""
    residual = ((prediction - truth) ** 2).sum(axis=0)
    total = ((truth - truth.mean(axis=0)) ** 2).sum(axis=0)
    return 1.0 - residual / np.where(total > 0, total, np.nan)


def _finite(values: np.ndarray, names: list[str]) -> dict[str, float | None]:
    return {n: (float(v) if np.isfinite(v) else None) for n, v in zip(names, values)}


def evaluate(net: MesoNet, db: Database, index: np.ndarray) -> dict[str, dict[str, float | None]]:
    """R^2 per learned output on samples ``index`` (see the module docstring).

    Returns ``{"rate": {"x_n3": ...}, "relaxation": {...}, "moment_increment": {"S_nn": ..., "S_tt": ...}}``
    (3D: ``S_nn, S_t1t1, S_t2t2``); DOF names are ``x_{axis}{grain label}``; None where the set has no spread.
    """
    free = db.schema.free_dofs.numpy()
    axes = AXIS_NAMES[db.schema.dim]
    names = [f"x_{axes[a]}{g + 1}" for g, a in free]
    state = [torch.from_numpy(db.before[k][index]) for k in ("cell_size", "free_position", "shear_force")]
    d_eps = torch.from_numpy(db.d_eps[index])
    with torch.no_grad():
        predicted = net.displacement(*state, d_eps).numpy()
        ann = cell_physics.advance(db.schema, *state, d_eps, torch.from_numpy(predicted)).moment.numpy()
        dem = cell_physics.advance(db.schema, *state, d_eps, torch.from_numpy(
            db.after_free_position[index] - db.before["free_position"][index])).moment.numpy()
        x = cell_physics.positions(db.schema, state[0], state[1])
        c = cell_physics.contacts(db.schema, x)
        before = cell_physics.love_weber(c, cell_physics.pair_forces(c, state[2])).numpy()
    truth = db.after_free_position[index] - db.before["free_position"][index]
    m = np.linalg.norm(db.d_eps[index], axis=1)
    clean = ~db.perturbed[index] & (m > 0)
    diameter = db.schema.diameter
    diagonal = list(range(db.schema.dim))
    diag = (slice(None), diagonal, diagonal)
    return {
        "rate": _finite(r2(predicted[clean] / (diameter * m[clean, None]), truth[clean] / (diameter * m[clean, None])), names),
        "relaxation": _finite(r2(predicted[~clean] / diameter, truth[~clean] / diameter), names),
        "moment_increment": _finite(r2(ann[diag] - before[diag], dem[diag] - before[diag]),
                                    [f"S_{a}{a}" for a in axes]),
    }


def _plot_learning_curve(path: Path, history: dict) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), layout="constrained")
    ax.semilogy(history["epoch"], history["train_loss"], label="training")
    ax.semilogy(history["epoch"], history["val_loss"], label="validation")
    ax.axvline(history["best_epoch"], color="0.6", ls=":", label=f"best epoch {history['best_epoch']}")
    ax.set_xlabel("epoch [-]")
    ax.set_ylabel("relative MSE of free-DOF displacements [-]")
    ax.legend()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _warm_line(warm: dict) -> str:
    """The summary line of a warm start."""
    if warm["used"]:
        return f"warm start from {warm['from']} (feature scaling recomputed, weights re-expressed in it)"
    return f"warm start from {warm['from']} declined: {warm['reason']}; trained from random weights"


def _dof_name(db: Database, k: int) -> str:
    """Name of free DOF ``k``: 1-based grain and local axis (e.g. ``x_t1 of grain 11``)."""
    grain, axis = (int(v) for v in db.schema.free_dofs[k])
    return f"x_{AXIS_NAMES[db.schema.dim][axis]} of grain {grain + 1}"


def _format_r2(metrics: dict) -> str:
    return "  ".join(f"{group}:{k}={'-' if v is None else f'{v:.5f}'}" for group, values in metrics.items()
                     for k, v in values.items())


def _silent(*_lines: str) -> None:
    """The ``log`` callback that reports nothing."""


def train_and_save(data: Path, out: Path, config: TrainConfig = TrainConfig(), *, overwrite: bool = False,
                   command: str | None = None, progress: Progress | None = None,
                   log: Callable[..., None] = _silent) -> Path:
    """Train a model on database ``data`` with ``config`` and write ``out`` (the state_dict), its
    ``.json`` (metadata), its learning curve and its out-of-distribution index (module docstring);
    returns ``out``. ``command`` is recorded in the JSON (None: this process's command line);
    ``progress`` receives each epoch (``fit``); ``log`` the summary lines (one string each).

    Raises:
        DataError (one line, before any training): ``out`` (or its .json/.png) exists without
            ``overwrite``, is a folder, does not end in .pt or cannot be written; ``config.init_from`` is no file; ``data``
            is no learning database.
    """
    out = Path(out)
    curve = out.with_name(f"{out.stem}_learning_curve.png")
    if not overwrite and any(p.exists() for p in (out, out.with_suffix(".json"), curve)):
        raise DataError(f"{out} (or its .json/.png) exists; pass --overwrite to replace it")
    if out.is_dir():
        raise DataError(f"--out {out} is a folder; give a file name")
    if out.suffix != ".pt":
        raise DataError(f"--out {out}: the model's file name ends in .pt (its metadata go to the .json beside it)")
    if config.init_from is not None and not Path(config.init_from).is_file():
        raise DataError(f"--init-from {config.init_from}: no such model file")
    check_output_path(out, overwrite=True)  # writable, checked before training
    with output_lock(out):
        _train(Path(data), out, curve, config, shlex.join(sys.argv) if command is None else command, progress, log)
    return out


def _train(data: Path, out: Path, curve: Path, config: TrainConfig, command: str, progress: Progress | None,
           log: Callable[..., None]) -> None:
    """Train, evaluate and write the model of ``train_and_save`` (holding the output lock)."""
    db = load_database(data)
    result = fit(db, config, progress=progress)
    metrics = {name: evaluate(result.net, db, getattr(result.split, name)) for name in ("train", "val", "test")}
    law = ContactLaw(kn=db.kn, kt_over_kn=db.kt_over_kn, phi_g_deg=db.phi_g_deg)
    rollout = (rollout_report(result.net, from_description(db.mesostructure), law, DemSettings(contact_tolerance=db.contact_tolerance))
               if config.rollout else None)
    split = result.split
    metadata = {
        "contact_law": {"kn": db.kn, "kt_over_kn": db.kt_over_kn, "phi_g_deg": db.phi_g_deg},
        "contact_tolerance": db.contact_tolerance,
        "schema": {k: np.asarray(v).tolist() for k, v in db.schema_arrays.items()},
        "mesostructure": db.mesostructure,
        "mesostructure_sha256": db.mesostructure_sha256,
        "start_mesostructures": list(db.start_mesostructures),
        "target": "free-DOF displacement d_free = D |d_eps| r - C F / kn (training.network)",
        "training_data": {"path": str(data), "sha256": db.sha256, "n_stored": db.n_stored,
                          "n_selected": db.n_samples, "n_unconverged_dropped": db.n_unconverged,
                          "n_jumps_dropped": db.n_jumps, "n_perturbed": int(db.perturbed.sum()),
                          "n_mechanism": int(db.mechanism.sum()), "n_train": int(split.train.size),
                          "n_val": int(split.val.size), "n_test": int(split.test.size),
                          "degenerate_rates": [_dof_name(db, k) for k in result.normalisation.degenerate_rates]},
        "config": config_record(config),
        "metrics_r2": metrics,
        "rollout": rollout,
        "history": {"best_epoch": result.history["best_epoch"], "seconds": result.history["seconds"],
                    "epochs_run": len(result.history["epoch"]), "best_val_loss": min(result.history["val_loss"]),
                    "warm_start": result.history["warm_start"]},
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
                     "git_revision": git_revision()},
        "command": command,
    }
    save_checkpoint(out, result.net, metadata)
    ood_file = index_for_model(result.net, metadata["config"], db).save(index_path(out))
    _plot_learning_curve(curve, result.history)
    log(f"trained {len(result.history['epoch'])} epochs in {result.history['seconds']:.1f} s "
        f"(best epoch {result.history['best_epoch']}); samples train/val/test = "
        f"{split.train.size}/{split.val.size}/{split.test.size}",
        *(f"R^2 {name:>4}: {_format_r2(metrics[name])}" for name in ("val", "test")),
        *([] if result.history["warm_start"] is None else [_warm_line(result.history["warm_start"])]),
        *([f"degenerate rates (moved by round-off only; standard deviation set to 1): "
           f"{', '.join(metadata['training_data']['degenerate_rates'])}"] if result.normalisation.degenerate_rates else []))
    if rollout is not None:
        log(*(f"rollout error ({key}): max {value['max']:.4f}, median {value['median']:.4f} of the path's largest |S|"
              for key, value in rollout.items() if key.startswith("increment_")))
    log(f"wrote {out}, {out.with_suffix('.json')}, {curve}, {ood_file} (out-of-distribution index)",
        f"the model is UNCERTIFIED: the ANN backend refuses it until it passes "
        f"python -m homogenization.certify --model {out} --write (docs/certificate.md)")


