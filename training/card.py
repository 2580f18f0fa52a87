"""The model card: a meso-ANN's JSON metadata (``NAME.json`` beside ``NAME.pt``) as a record.

``ModelCard.to_dict`` gives back the mapping ``from_dict`` read, key for key (``certificate`` and
``active_learning`` absent where None; the training's keys present, null included), so a file read
and written again (``write_card``) is the same bytes. The certificate and the rounds stay mappings
here: their records belong to the learning loop (``homogenization.ann.records``), which
``training`` does not import.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Mapping

from training.checkpoint import CheckpointError, metadata_path, read_metadata
from training.record_io import record_dict, record_keywords
from warp_hcell.core.files import atomic_write
from warp_hcell.core.parameters import ContactLaw


@dataclass(frozen=True)
class ModelCard:
    """A model's JSON metadata (``training.checkpoint.save_checkpoint``, ``training.train``)."""

    OPTIONAL: ClassVar[frozenset[str]] = frozenset({"certificate", "active_learning"})
    """Keys written only where the card holds them (None: absent)."""

    format: str
    """``training.checkpoint.FORMAT``."""
    format_version: int
    """``training.checkpoint.FORMAT_VERSION`` (also the version of the certificate's and rounds' records)."""
    architecture: dict[str, Any]
    """``hidden`` widths, ``activation``, ``n_free``, ``active_pairs``, ``load_features``."""
    normalisation: dict[str, Any]
    """``feature_mean``, ``feature_std``, ``rate_mean``, ``rate_std`` (lists)."""
    schema: dict[str, Any]
    """The database's schema arrays, as lists."""
    contact_law: dict[str, float]
    """``kn`` [N/m], ``kt_over_kn`` [-], ``phi_g_deg`` [deg] (``law``)."""
    contact_tolerance: float
    """The DEM's contact tolerance of the database [-]."""
    mesostructure: str
    """The database's mesostructure description."""
    mesostructure_sha256: str
    """Its sha256."""
    start_mesostructures: list[str]
    """The cells the database was explored from."""
    target: str
    """What the network predicts, in words."""
    training_data: dict[str, Any]
    """``path``, ``sha256`` of the database trained on, and its sample counts."""
    config: dict[str, Any]
    """The training configuration (``training.config.config_record``)."""
    metrics_r2: dict[str, Any]
    """R^2 per split and output."""
    rollout: dict[str, Any] | None
    """The single-cell rollouts (``training.rollout.rollout_report``); None: not run."""
    history: dict[str, Any]
    """``best_epoch``, ``seconds``, ``epochs_run``, ``best_val_loss``, ``warm_start``."""
    versions: dict[str, Any]
    """python, torch, numpy, git revision."""
    command: str | None
    """The command line that trained it."""
    certificate: dict[str, Any] | None = None
    """The certificate (``homogenization.ann.records.Certificate.to_dict``); None: uncertified."""
    active_learning: list[dict[str, Any]] | None = None
    """The active-learning rounds (``homogenization.ann.records.Round.to_dict``); None: none run."""

    @property
    def law(self) -> ContactLaw:
        """The contact law the model was trained for."""
        return ContactLaw.from_dict(self.contact_law)

    def to_dict(self) -> dict[str, Any]:
        """The card as its JSON holds it."""
        return record_dict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "ModelCard":
        """The card of its ``to_dict`` (ValueError, one line, for an unknown or missing key)."""
        return cls(**record_keywords(cls, values))


def read_card(path: str | Path) -> ModelCard:
    """The card of model ``path`` (the ``.pt`` or its ``.json``); CheckpointError (one line) where
    the JSON is missing, unreadable or no card (``training.checkpoint.read_metadata``)."""
    try:
        return ModelCard.from_dict(read_metadata(path))
    except ValueError as exc:
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(f"{metadata_path(path)}: {exc}") from None


def write_card(path: str | Path, card: ModelCard) -> Path:
    """Write ``card`` as model ``path``'s JSON (atomically; ``indent=2``, sorted keys); returns the JSON path."""
    json_path = metadata_path(path)
    with atomic_write(json_path) as tmp:
        tmp.write_text(json.dumps(card.to_dict(), indent=2, sort_keys=True) + "\n")
    return json_path
