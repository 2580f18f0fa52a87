"""The cleaning step of the learning database: marks samples the network must not learn from
in ``valid`` and records what it removed. Nothing is deleted: a removed sample stays in the
file with ``valid = False``, so the step can be audited and undone. Mechanism (stress-free)
and perturbed samples are kept: the network must learn them.

A sample is removed for each of these reasons (``REASONS``; a sample may have several):

- ``unconverged``: the DEM did not reach quasi-static equilibrium within max_substeps
  (``converged`` False);
- ``non_finite``: a non-finite value in ``d_eps`` or in a state before or after the probe.

Root attrs written: ``cleaned`` (bool), ``n_valid``, ``removed_<reason>`` (count per
reason), ``n_removed`` (samples with at least one reason) and ``cleaning`` (JSON: rules and
counts). Without cleaning (``not_cleaned``) every sample is valid and ``cleaned`` is False.
``clean_file`` rewrites the file atomically (temporary file, then rename): an interrupted run
leaves the original intact. The command is ``python -m warp_hcell.clean``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from warp_hcell.database import format as database

REASONS = {
    "unconverged": "the DEM did not reach quasi-static equilibrium within max_substeps",
    "non_finite": "non-finite value in d_eps or in the state before or after the probe",
}
"""Cleaning reasons and their rules."""


def pathological(data: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-reason masks of the samples to remove.

    Args:
        data: database datasets keyed by HDF5 path (at least ``converged``, ``d_eps`` and the
            groups ``before``/``after``).

    Returns:
        ``REASONS`` key -> bool array (n_samples,), True = remove.
    """
    finite = np.isfinite(data["d_eps"]).all(axis=1)
    for name, value in data.items():
        if name.split("/")[0] in database.STATE_GROUPS:
            value = np.asarray(value)
            finite &= np.isfinite(value.reshape(value.shape[0], -1)).all(axis=1)
    return {"unconverged": ~np.asarray(data["converged"], dtype=bool), "non_finite": ~finite}


def _attrs(valid: np.ndarray, masks: Mapping[str, np.ndarray] | None) -> dict[str, Any]:
    removed = {reason: int(np.count_nonzero(mask)) for reason, mask in (masks or {}).items()}
    attrs: dict[str, Any] = {"cleaned": masks is not None, "n_valid": int(np.count_nonzero(valid)),
                             "n_removed": int(valid.size - np.count_nonzero(valid))}
    attrs.update({f"removed_{reason}": count for reason, count in removed.items()})
    attrs["cleaning"] = json.dumps({"applied": masks is not None, "rules": REASONS if masks is not None else {},
                                    "removed": removed}, sort_keys=True)
    return attrs


def clean_samples(data: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
    """Apply the cleaning rules.

    Returns:
        (valid (n_samples,) bool, root attrs describing what was removed).
    """
    masks = pathological(data)
    valid = ~np.logical_or.reduce(list(masks.values()))
    return valid, _attrs(valid, masks)


def not_cleaned(data: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
    """Every sample valid, and the attrs saying that no cleaning was applied."""
    valid = np.ones(np.shape(data["converged"])[0], dtype=bool)
    return valid, _attrs(valid, None)


def clean_file(path: Path, out: Path) -> dict[str, Any]:
    """Clean database ``path`` and write it to ``out`` (may equal ``path``) atomically.

    Returns:
        The cleaning attrs written.
    """
    data, attrs = database.read_database(path)
    attrs_of = database.read_attrs_of(path)
    data["valid"], cleaning_attrs = clean_samples(data)
    attrs.update(cleaning_attrs)
    database.write_database(Path(out), data, attrs, attrs_of)
    return cleaning_attrs
