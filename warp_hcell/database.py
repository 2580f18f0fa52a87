"""The learning-database file format (docs/database_format.md): names, units, writer, reader.

This module is the single place that knows the HDF5 layout shared by the generator
(``warp_hcell.generate``), the cleaning step (``warp_hcell.clean``) and the training
pipeline. It exports:

- the column names and units of every 2-D dataset (``INPUT_FEATURES``, ``OUTPUT_FEATURES``,
  ``STATE_FEATURES``, ``UNITS``) and the root constants (``FORMAT``, ``FORMAT_VERSION``,
  ``SIGN_CONVENTION``);
- ``state_table``: a backend's ``observables`` dict -> the (n, 13) state columns;
- ``sample_arrays``: probes, pre/post states -> the per-sample datasets;
- ``write_database`` / ``read_database``: the whole file, written atomically (temporary
  file renamed into place, so a failure never leaves a truncated database).

Sign convention: compression and contraction positive (probe strains, N1, N2, S);
T1 > 0 resists opening. Local frame: index 0 = n, 1 = t. Lengths in m, forces in N (2D,
per unit thickness), angles in degrees (``_deg``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Mapping

import h5py
import numpy as np

FORMAT = "meso-hmodel-database"
"""Value of the root attr ``format``."""
FORMAT_VERSION = 1
"""Value of the root attr ``format_version``; bumped only for incompatible changes."""
SIGN_CONVENTION = (
    "compression and contraction positive (d_eps_n, d_eps_t, N1, N2, S_nn, S_tt); "
    "T1 > 0 resists opening (alpha growing); local frame index 0 = n (cell axis), 1 = t"
)
"""Value of the root attr ``sign_convention``."""

INPUT_FEATURES = ("d_eps_n", "d_eps_t", "alpha_deg", "N1", "N2", "T1", "l1", "l2")
"""Columns of ``inputs``: the probe and the PRE-increment state."""
OUTPUT_FEATURES = ("alpha_deg", "N1", "N2", "T1")
"""Columns of ``outputs``: the POST-increment state."""
STATE_FEATURES = ("l1", "l2", "alpha_deg", "d1", "d2", "N1", "N2", "T1", "S_nn", "S_tt", "area", "closed1", "closed2")
"""Columns of ``pre_state`` / ``post_state`` (``closed1``, ``closed2`` stored as 0.0 / 1.0)."""

UNITS = {
    "d_eps_n": "-",
    "d_eps_t": "-",
    "alpha_deg": "deg",
    "N1": "N",
    "N2": "N",
    "T1": "N",
    "l1": "m",
    "l2": "m",
    "d1": "m",
    "d2": "m",
    "S_nn": "N m",
    "S_tt": "N m",
    "area": "m^2",
    "closed1": "bool",
    "closed2": "bool",
}
"""Unit of every feature name."""

SAMPLE_DATASETS = {
    "inputs": "probe (d_eps_n, d_eps_t) and the pre-increment state",
    "outputs": "post-increment state",
    "pre_state": "cell state before the probe",
    "post_state": "cell state after the probe",
    "path_id": "exploration path the state was sampled from (split by path, never by sample)",
    "probe_id": "index of the probe among the probes of its state",
    "alpha0_deg": "initial opening angle of the path",
    "state_index": "row of the pre-increment state in the group 'states'",
    "converged": "the backend reached quasi-static equilibrium for this probe",
    "valid": "False for samples removed by the cleaning step (see 'cleaning' attrs)",
}
"""Per-sample datasets (first axis n_samples) and their descriptions."""

STATES_GROUP = "states"
"""Group holding the sampled exploration states: the backend's ``state_to_arrays`` (one
dataset per field, first axis n_states) plus ``observables`` (n_states, 13) and the path
description datasets; ``state_index`` points into it."""


def state_table(observables: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``STATE_FEATURES`` columns of a backend's observables.

    Args:
        observables: ``CellModel.observables`` output, each value shape (n_cells,).

    Returns:
        float64 array, shape (n_cells, 13), columns ``STATE_FEATURES`` (flags as 0/1).
    """
    return np.stack([np.asarray(observables[name], dtype=np.float64) for name in STATE_FEATURES], axis=1)


def sample_arrays(d_eps_local: np.ndarray, pre: np.ndarray, post: np.ndarray) -> dict[str, np.ndarray]:
    """``inputs``, ``outputs``, ``pre_state`` and ``post_state`` of a batch of probes.

    Args:
        d_eps_local: probe (d_eps_n, d_eps_t) [-], shape (n, 2), compression positive.
        pre: state before the probe, shape (n, 13), columns ``STATE_FEATURES``.
        post: state after the probe, shape (n, 13), columns ``STATE_FEATURES``.
    """
    column = {name: i for i, name in enumerate(STATE_FEATURES)}
    inputs = np.concatenate([d_eps_local, pre[:, [column[name] for name in INPUT_FEATURES[2:]]]], axis=1)
    outputs = post[:, [column[name] for name in OUTPUT_FEATURES]]
    return {"inputs": inputs, "outputs": outputs, "pre_state": pre, "post_state": post}


def _attr(value: Any) -> Any:
    """HDF5-storable form of an attribute: dicts and lists of non-strings become JSON."""
    if isinstance(value, Mapping):
        return json.dumps(value, sort_keys=True)
    return value


def write_database(
    path: Path,
    samples: Mapping[str, np.ndarray],
    states: Mapping[str, np.ndarray],
    attrs: Mapping[str, Any],
) -> None:
    """Write a complete database file atomically.

    The file is written under a temporary name in the same folder and renamed onto
    ``path`` only once complete, so an existing database is replaced whole or not at all.
    No timestamps are stored, so the same arrays and attrs give a byte-identical file.

    Args:
        path: file to create or replace.
        samples: every dataset of ``SAMPLE_DATASETS`` (first axis n_samples).
        states: datasets of the ``states`` group (first axis n_states).
        attrs: root attributes; mappings are stored as JSON strings.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        _write_file(tmp, samples, states, attrs)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _write_file(
    path: Path,
    samples: Mapping[str, np.ndarray],
    states: Mapping[str, np.ndarray],
    attrs: Mapping[str, Any],
) -> None:
    feature_names = {"inputs": INPUT_FEATURES, "outputs": OUTPUT_FEATURES}
    feature_names.update({"pre_state": STATE_FEATURES, "post_state": STATE_FEATURES})
    with h5py.File(path, "w", track_order=True) as f:
        for key, value in attrs.items():
            f.attrs[key] = _attr(value)
        for name, description in SAMPLE_DATASETS.items():
            data = np.asarray(samples[name])
            dset = f.create_dataset(name, data=data, track_times=False)
            dset.attrs["description"] = description
            if name in feature_names:
                dset.attrs["feature_names"] = list(feature_names[name])
                dset.attrs["units"] = [UNITS[column] for column in feature_names[name]]
            else:
                dset.attrs["units"] = "deg" if name.endswith("_deg") else "-"
        group = f.create_group(STATES_GROUP, track_order=True)
        group.attrs["description"] = "sampled exploration states: backend state arrays and their observables"
        for name, value in states.items():
            group.create_dataset(name, data=np.asarray(value), track_times=False)
        group["observables"].attrs["feature_names"] = list(STATE_FEATURES)
        group["observables"].attrs["units"] = [UNITS[column] for column in STATE_FEATURES]


def read_database(path: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, Any]]:
    """Read a database file written by ``write_database``.

    Returns:
        (samples, states, attrs): per-sample arrays keyed like ``SAMPLE_DATASETS``, the
        ``states`` group arrays, and the root attrs (JSON strings left as stored).

    Raises:
        ValueError: (one line) if ``path`` is not a readable HDF5 database of this format version.
    """
    try:
        handle = h5py.File(path, "r")
    except OSError:
        raise ValueError(f"{path}: not a readable HDF5 file") from None
    with handle as f:
        if f.attrs.get("format") != FORMAT or int(f.attrs.get("format_version", -1)) != FORMAT_VERSION:
            raise ValueError(f"{path} is not a {FORMAT} file of format_version {FORMAT_VERSION}")
        samples = {name: f[name][()] for name in SAMPLE_DATASETS}
        states: dict[str, np.ndarray] = {}
        f[STATES_GROUP].visititems(
            lambda name, item: states.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None)
        attrs = dict(f.attrs)
    return samples, states, attrs
