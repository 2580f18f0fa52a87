"""Model checkpoints: a torch ``state_dict`` (``NAME.pt``) plus JSON metadata (``NAME.json``).

Contract:

- ``save_checkpoint(path, net, metadata)`` writes both files atomically (a failure never
  leaves a truncated file in place of a good one). The JSON holds the architecture, the
  normalisation statistics and scales, and whatever the caller adds (contact law, radius,
  training-data hash, metrics, training configuration, versions).
- ``load_checkpoint(path)`` rebuilds a ``CellNet`` from the JSON architecture and loads the
  ``state_dict`` with ``torch.load(weights_only=True)``: no pickled module is ever executed.
  A missing, corrupt or mismatched pair raises ``CheckpointError`` (one line).
- ``check_compatible`` refuses a model trained for another contact law or grain radius.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import torch

from training.network import ACTIVATION, N_INPUTS, N_OUTPUTS, CellNet

FORMAT = "meso-hmodel-ann"
"""Value of the metadata key ``format``."""
FORMAT_VERSION = 1
"""Supported metadata ``format_version``."""


class CheckpointError(ValueError):
    """A model file pair that cannot be used; the message is one line naming the file."""


def metadata_path(path: str | Path) -> Path:
    """JSON metadata file that goes with the state_dict file ``path`` (same stem, ``.json``)."""
    return Path(path).with_suffix(".json")


def _replace_atomically(path: Path, write) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o644)  # mkstemp makes 0600 files; a model is meant to be shared
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def architecture(net: CellNet) -> dict[str, Any]:
    """JSON description of ``net``'s architecture, enough to rebuild it."""
    return {"n_inputs": N_INPUTS, "n_outputs": N_OUTPUTS, "hidden": list(net.hidden), "activation": ACTIVATION}


def save_checkpoint(path: str | Path, net: CellNet, metadata: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``net.state_dict()`` to ``path`` and metadata to ``metadata_path(path)``.

    ``metadata`` is extended with the format tag, the architecture, the scales (kn [N/m],
    diameter [m], mu [-]) and the normalisation statistics (copies of the buffers, for readers
    without torch). Returns the two paths written.
    """
    path = Path(path)
    buffers = {name: getattr(net, name).tolist() for name in ("feature_mean", "feature_std", "rate_mean", "rate_std")}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": architecture(net),
        "scales": {"kn": float(net.kn), "diameter": float(net.diameter), "mu": float(net.mu)},
        "normalisation": buffers,
        **metadata,
    }
    state = {key: value.detach().clone() for key, value in net.state_dict().items()}
    _replace_atomically(path, lambda tmp: torch.save(state, tmp))
    json_path = metadata_path(path)
    _replace_atomically(json_path, lambda tmp: tmp.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n"))
    return path, json_path


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The checked JSON metadata of model ``path`` (the ``.pt`` or the ``.json`` file)."""
    json_path = metadata_path(path)
    if not json_path.is_file():
        raise CheckpointError(f"{json_path}: no such model metadata file")
    try:
        meta = json.loads(json_path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise CheckpointError(f"{json_path}: not a valid JSON model metadata file") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{json_path}: not a {FORMAT} metadata file")
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{json_path}: format_version {meta.get('format_version')!r} is not supported (expected {FORMAT_VERSION})")
    arch = meta.get("architecture")
    expected = {"n_inputs": N_INPUTS, "n_outputs": N_OUTPUTS, "activation": ACTIVATION}
    if not isinstance(arch, dict) or any(arch.get(k) != v for k, v in expected.items()) or not isinstance(arch.get("hidden"), list):
        raise CheckpointError(f"{json_path}: architecture {arch!r} is not a {N_INPUTS}-input {ACTIVATION} CellNet")
    return meta


def load_checkpoint(path: str | Path) -> tuple[CellNet, dict[str, Any]]:
    """Rebuild the network saved at ``path``; returns ``(net in eval mode, metadata)``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such model file")
    meta = read_metadata(path)
    try:
        net = CellNet(meta["architecture"]["hidden"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{metadata_path(path)}: {exc}") from None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # torch raises several types (pickle, zip, runtime) for a corrupt file
        raise CheckpointError(f"{path}: not a readable torch state_dict") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not a torch state_dict")
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError:
        raise CheckpointError(f"{path}: state_dict does not match the architecture in {metadata_path(path).name} (hidden = {meta['architecture']['hidden']})") from None
    scales = meta.get("scales", {})
    if not all(math.isclose(float(getattr(net, k)), float(scales.get(k, math.nan)), rel_tol=1e-12) for k in ("kn", "diameter", "mu")):
        raise CheckpointError(f"{path}: scales in the state_dict differ from {metadata_path(path).name}")
    return net.eval(), meta


def check_compatible(meta: dict[str, Any], *, kn: float, kt_over_kn: float, phi_g_deg: float, radius: float, source: str) -> None:
    """Raise ``CheckpointError`` unless the model was trained with this contact law and radius.

    Args:
        meta: metadata of ``load_checkpoint``; its ``contact_law`` holds ``kn`` [N/m],
            ``kt_over_kn`` [-], ``phi_g_deg`` [deg], and ``radius`` [m] the grain radius.
        source: file name used in the message.
    """
    law = meta.get("contact_law", {})
    trained = {"kn": law.get("kn"), "kt_over_kn": law.get("kt_over_kn"), "phi_g_deg": law.get("phi_g_deg"), "radius": meta.get("radius")}
    wanted = {"kn": kn, "kt_over_kn": kt_over_kn, "phi_g_deg": phi_g_deg, "radius": radius}
    for name, value in wanted.items():
        have = trained[name]
        if not isinstance(have, (int, float)) or not math.isclose(float(have), float(value), rel_tol=1e-9):
            raise CheckpointError(f"{source}: model trained with {name} = {have}, this run uses {name} = {value:g}")
