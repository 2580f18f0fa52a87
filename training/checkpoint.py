"""Model checkpoints: a torch ``state_dict`` (``NAME.pt``) plus JSON metadata (``NAME.json``).

Contract:

- ``save_checkpoint(path, net, metadata)`` writes both files atomically (a failure never
  leaves a truncated file in place of a good one). The JSON holds the architecture, the
  mesostructure schema (topology and reference geometry), the contact law, the
  mesostructure description and its sha256, the normalisation statistics and whatever the
  caller adds (training-data hash, metrics, configuration, versions).
- ``load_checkpoint(path[, metadata])`` rebuilds a ``MesoNet`` from the JSON and loads the
  ``state_dict`` with ``torch.load(weights_only=True)``: no pickled module is ever executed.
  A missing, corrupt or mismatched pair raises ``CheckpointError`` (one line).
- ``check_compatible`` refuses a model trained for another contact law;
  ``check_start_cell`` a cell the model's database was not explored from (another
  mesostructure, or a cell of the same learning state outside the range of its start cells).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from training.fast_model import ACTIVATION
from warp_hcell.core.files import atomic_write
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.files import describe, description_sha256, from_description
from warp_hcell.mesostructures.mesostructure import Mesostructure, shares_state_schema

if TYPE_CHECKING:
    from training.network import MesoNet

FORMAT = "meso-hmodel-ann"
"""Value of the metadata key ``format``."""
FORMAT_VERSION = 2
"""Supported metadata ``format_version`` (the generic meso-ANN)."""


class CheckpointError(ValueError):
    """A model file pair that cannot be used; the message is one line naming the file."""


def metadata_path(path: str | Path) -> Path:
    """JSON metadata file that goes with the state_dict file ``path`` (same stem, ``.json``)."""
    return Path(path).with_suffix(".json")


def save_checkpoint(path: str | Path, net: MesoNet, metadata: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``net.state_dict()`` to ``path`` and metadata to ``metadata_path(path)``.

    ``metadata`` must hold ``schema`` (the database's schema arrays as lists),
    ``contact_law`` (kn [N/m], kt_over_kn [-], phi_g_deg [deg]), ``contact_tolerance`` [-],
    ``mesostructure`` and ``mesostructure_sha256``; it is extended with the format tag, the
    architecture and the normalisation statistics (copies of the buffers, for readers
    without torch). Returns the two paths written.
    """
    import torch  # noqa: PLC0415 (torch only where a network is saved or rebuilt: compiled inference reads without it)

    path = Path(path)
    buffers = {name: getattr(net, name).tolist() for name in ("feature_mean", "feature_std", "rate_mean", "rate_std")}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "architecture": {"hidden": list(net.hidden), "activation": ACTIVATION, "n_free": net.n_free,
                         "active_pairs": [bool(a) for a in net.active.tolist()],
                         "load_features": net.load_features},
        "normalisation": buffers,
        **metadata,
    }
    state = {key: value.detach().clone() for key, value in net.state_dict().items()}
    with atomic_write(path) as tmp, open(tmp, "wb") as handle:
        torch.save(state, handle)  # a file object: the archive's record names do not carry the temporary name
    json_path = metadata_path(path)
    with atomic_write(json_path) as tmp:
        tmp.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
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
        raise CheckpointError(f"{json_path}: format_version {meta.get('format_version')!r} is not supported "
                              f"(expected {FORMAT_VERSION}: the generic meso-ANN); retrain the model")
    for key in ("architecture", "schema", "contact_law", "contact_tolerance", "mesostructure_sha256"):
        if key not in meta:
            raise CheckpointError(f"{json_path}: missing {key!r}")
    arch = meta["architecture"]
    if not isinstance(arch, dict) or arch.get("activation") != ACTIVATION or not isinstance(arch.get("hidden"), list):
        raise CheckpointError(f"{json_path}: architecture {arch!r} is not a {ACTIVATION} MesoNet")
    return meta


def load_checkpoint(path: str | Path, metadata: dict[str, Any] | None = None) -> tuple[MesoNet, dict[str, Any]]:
    """Rebuild the network saved at ``path``; returns ``(net in eval mode, metadata)``. ``metadata``:
    its JSON as ``read_metadata`` gave it (None: read here)."""
    import torch  # noqa: PLC0415 (as in save_checkpoint)

    from training.dataset import SCHEMA_FIELDS, schema_from_arrays  # noqa: PLC0415
    from training.network import MesoNet  # noqa: PLC0415

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such model file")
    meta = read_metadata(path) if metadata is None else metadata
    try:
        law = ContactLaw.from_dict(meta["contact_law"])
        schema_arrays = {k: np.asarray(meta["schema"][k]) for k in SCHEMA_FIELDS}
        schema = schema_from_arrays(schema_arrays, kn=float(law.kn), kt_over_kn=float(law.kt_over_kn),
                                    phi_g_deg=float(law.phi_g_deg), contact_tolerance=float(meta["contact_tolerance"]))
        net = MesoNet(schema, torch.tensor(meta["architecture"]["active_pairs"], dtype=torch.bool),
                      meta["architecture"]["hidden"], bool(meta["architecture"].get("load_features", False)))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"{metadata_path(path)}: cannot rebuild the network ({exc})") from None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # torch raises several types (pickle, zip, runtime) for a corrupt file
        raise CheckpointError(f"{path}: not a readable torch state_dict") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: not a torch state_dict")
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError:
        raise CheckpointError(f"{path}: state_dict does not match the architecture in {metadata_path(path).name}") from None
    return net.eval(), meta


def check_compatible(meta: dict[str, Any], *, kn: float, kt_over_kn: float, phi_g_deg: float, source: str) -> None:
    """Raise ``CheckpointError`` unless the model was trained with this contact law.

    Args:
        meta: metadata of ``load_checkpoint``; its ``contact_law`` holds ``kn`` [N/m],
            ``kt_over_kn`` [-], ``phi_g_deg`` [deg].
        source: file name used in the message.
    """
    law = meta.get("contact_law", {})
    for name, value in {"kn": kn, "kt_over_kn": kt_over_kn, "phi_g_deg": phi_g_deg}.items():
        have = law.get(name)
        if not isinstance(have, (int, float)) or not math.isclose(float(have), float(value), rel_tol=1e-9):
            raise CheckpointError(f"{source}: model trained with {name} = {have}, this run uses {name} = {value:g}")


def _start_coordinates(meso: Mesostructure) -> np.ndarray:
    """Cell size and free-DOF coordinates of a cell's start state [m], shape (2 + n_free,)."""
    return np.concatenate([meso.cell_size, meso.position[~meso.driven]])


def check_start_cell(meta: dict[str, Any], meso: Mesostructure, *, source: str) -> None:
    """Raise ``CheckpointError`` (one line) unless the model may start cells from ``meso``.

    Accepted: the mesostructure of the model's database (same sha256), or a cell of the same
    learning state (``shares_state_schema``) whose start state -- cell size and free-DOF
    coordinates -- lies within the range spanned by the cells the database was explored from
    (``start_mesostructures``; the mesostructure alone for a model without them), to 1e-9 of
    the largest grain radius. Nothing here knows the shape of a cell.
    """
    if description_sha256(describe(meso)) == meta.get("mesostructure_sha256"):
        return
    trained = from_description(meta["mesostructure"])
    starts = [from_description(text) for text in meta.get("start_mesostructures", [meta["mesostructure"]])]
    reason = "has another learning state (grains, pairs or driven DOFs)"
    if shares_state_schema(trained, meso):
        span = np.stack([_start_coordinates(start) for start in starts])
        slack = 1e-9 * float(np.max(meso.radius))
        mine = _start_coordinates(meso)
        if np.all((span.min(axis=0) - slack <= mine) & (mine <= span.max(axis=0) + slack)):
            return
        reason = "starts outside the range of the cells its database was explored from"
    raise CheckpointError(
        f"{source}: model trained on mesostructure {str(meta.get('mesostructure_sha256'))[:12]} and "
        f"{len(starts)} start cell(s); {meso.name!r} {reason}; train a model on a database of this mesostructure")
