"""The generic learning-database file format, version 2 (docs/database_format.md): writer, reader.

This module is the single place that knows the HDF5 layout shared by the generator
(``warp_hcell.generate``), the cleaning step (``warp_hcell.clean``) and the training
pipeline. One file holds the probes of ONE mesostructure (its description and hash are root
attributes); its learning state (``warp_hcell.core.contract.StateSchema``) is the group
``schema``; every sample is a state ``before`` and ``after`` one strain probe ``d_eps``.

Sign convention: compression and contraction positive (probe strains, normal forces,
moment); DEM arrays keep the DEM's conventions (``shear_force``: force on grain i along
w = (-u_t, u_n)). Local frame: index 0 = n, 1 = t. Lengths in m, forces in N (2D, per unit
thickness), angles in degrees (``_deg``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping

import h5py
import numpy as np

from warp_hcell.core.contract import StateSchema
from warp_hcell.core.files import atomic_write
from warp_hcell.mesostructures.mesostructure import AXIS_NAMES, OBSERVABLE_KINDS, Mesostructure, PairObservable

FORMAT = "meso-hmodel-database"
"""Value of the root attr ``format``."""
FORMAT_VERSION = 2
"""Value of the root attr ``format_version``; bumped only for incompatible changes."""
SIGN_CONVENTION = (
    "compression and contraction positive (d_eps, normal_force, moment); shear_force is the DEM's "
    "tangential spring force on grain i along w = (-u_t, u_n), u = (x_j - x_i)/|x_j - x_i|; "
    "local frame index 0 = n (cell axis), 1 = t"
)
"""Value of the root attr ``sign_convention``."""

STATE_GROUPS = ("before", "after")
"""Groups holding the state before and after each probe (datasets: the schema's features)."""
SAMPLE_DATASETS = {
    "d_eps": ("-", "probe (d_eps_n, d_eps_t), compression positive; zero for relaxation-only probes"),
    "mechanism": ("bool", "the before-state carries no contact force (every normal force <= "
                          "kn contact_tolerance D): a stress-free mechanism, kept"),
    "perturbed": ("bool", "the before-state is a sampled equilibrium state with its free DOFs displaced "
                          "at random; the DEM relaxes it during the probe"),
    "converged": ("bool", "the DEM reached equilibrium within max_substeps for this probe"),
    "state_id": ("-", "row of the sampled state the probe started from (group 'states')"),
    "path_id": ("-", "exploration path of that state (split by path, never by sample)"),
    "substeps": ("-", "DEM substeps the probe took"),
    "valid": ("bool", "False for samples removed by the cleaning step (see 'cleaning' attrs)"),
}
"""Root per-sample datasets (first axis n_samples): unit and description."""
OBSERVABLES_GROUP = "hcell"
"""Group of the observables the mesostructure declares (``Mesostructure.observables``, the
forces and geometry ones; e.g. the H-cell's alpha_deg, d1, d2, N1, N2, T1), before and after
each probe: for reports, never used by training or the ANN backend."""
SCHEMA_GROUP = "schema"
"""Group of the learning state of the mesostructure (same for every sample)."""
ACTIVE_GROUP = "active_states"
"""Group of the start states of the active-learning probes (``append_round``)."""
SCHEMA_DATASETS = ("free_dofs", "pairs", "radius", "reference_position", "reference_cell_size", "driven", "outer")
"""Datasets of the group ``schema`` (``StateSchema`` attributes)."""
COMPRESSION = {"compression": "gzip", "compression_opts": 4}
"""HDF5 filter of every dataset of ``COMPRESS_FROM`` elements or more: lossless (the arrays read back
are the bits written). Most of a fines cell's 55 candidate pairs carry no force (zero springs and normal
forces), which gzip packs best in whole samples without the shuffle filter (docs/database_format.md,
"Size")."""
COMPRESS_FROM = 1024
"""Elements [-] from which a dataset is stored compressed (smaller ones gain nothing)."""
CHUNK_BYTES = 1 << 20
"""Uncompressed bytes [B] of one HDF5 chunk of a compressed dataset, whole samples (rows) each (``chunk_rows``)."""


def chunk_rows(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """HDF5 chunk shape of a compressed dataset of ``shape`` and ``itemsize`` [B]: whole rows (samples), as many
    as fill ``CHUNK_BYTES`` (at least one, at most all)."""
    row = int(np.prod(shape[1:], dtype=np.int64)) * int(itemsize)
    return (max(1, min(int(shape[0]), CHUNK_BYTES // max(row, 1))), *shape[1:])


def schema_datasets(schema: StateSchema) -> dict[str, np.ndarray]:
    """The ``schema`` group datasets of a learning state, keyed ``schema/<name>``."""
    return {f"{SCHEMA_GROUP}/{name}": np.asarray(getattr(schema, name)) for name in SCHEMA_DATASETS}


def dataset_attrs(schema: StateSchema, meso: Mesostructure) -> dict[str, dict[str, Any]]:
    """Attributes (``feature_names``, ``units``, ``description``) of every dataset of a database of ``meso``."""
    attrs: dict[str, dict[str, Any]] = {}
    for group in STATE_GROUPS:
        for name, feature in schema.features.items():
            attrs[f"{group}/{name}"] = {"feature_names": list(feature.names), "units": feature.unit,
                                        "role": feature.role, "description": feature.description}
    for name, (unit, description) in SAMPLE_DATASETS.items():
        attrs[name] = {"units": unit, "description": description}
    attrs["d_eps"]["feature_names"] = ["d_eps_" + axis for axis in AXIS_NAMES[meso.dim]]
    attrs[SCHEMA_GROUP] = {"features": schema.feature_json(),
                           "feature_names": json.dumps({k: list(f.names) for k, f in schema.features.items()}),
                           "units": json.dumps({k: f.unit for k, f in schema.features.items()})}
    for name in meso.parameters:
        attrs[name] = {"description": f"parameter {name} of the start cell of the path"}
    for observable in stored_observables(meso):
        for group in STATE_GROUPS:
            attrs[f"{OBSERVABLES_GROUP}/{group}_{observable.name}"] = {"units": OBSERVABLE_KINDS[observable.kind][0]}
    return attrs


def stored_observables(meso: Mesostructure) -> tuple[PairObservable, ...]:
    """The declared observables stored in the group ``OBSERVABLES_GROUP``: all but the contact flags."""
    return tuple(o for o in meso.observables if o.kind != "contact")


def _attr(value: Any) -> Any:
    """HDF5-storable form of an attribute: mappings become JSON text."""
    if isinstance(value, Mapping):
        return json.dumps(value, sort_keys=True)
    return value


def write_database(path: Path, datasets: Mapping[str, np.ndarray], attrs: Mapping[str, Any],
                   attrs_of: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """Write a complete database file atomically (temporary file renamed onto ``path``).

    No timestamps are stored, so the same arrays and attrs give a byte-identical file. Datasets
    of ``COMPRESS_FROM`` elements or more are stored with the lossless ``COMPRESSION`` in chunks of whole
    rows (``chunk_rows``).

    Args:
        path: file to create or replace.
        datasets: arrays keyed by HDF5 path (``before/cell_size``, ``d_eps``, ...).
        attrs: root attributes; mappings are stored as JSON text.
        attrs_of: attributes of datasets or groups, keyed by HDF5 path (``dataset_attrs``).
    """
    with atomic_write(Path(path)) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            for key, value in attrs.items():
                f.attrs[key] = _attr(value)
            for name, value in datasets.items():
                value = np.asarray(value)
                packed = ({**COMPRESSION, "chunks": chunk_rows(value.shape, value.itemsize)}
                          if value.ndim and value.size >= COMPRESS_FROM else {})
                f.create_dataset(name, data=value, track_times=False, **packed)
            for name, values in (attrs_of or {}).items():
                if name in f:
                    for key, value in values.items():
                        f[name].attrs[key] = _attr(value)


def check_database(path: Path) -> None:
    """Raise ValueError (one line) unless ``path`` is a readable database of this format version."""
    try:
        handle = h5py.File(path, "r")
    except OSError:
        raise ValueError(f"{path}: not a readable HDF5 file") from None
    with handle as f:
        if f.attrs.get("format") != FORMAT or int(f.attrs.get("format_version", -1)) != FORMAT_VERSION:
            raise ValueError(f"{path} is not a {FORMAT} file of format_version {FORMAT_VERSION}")


def read_database(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a database file written by ``write_database``.

    Returns:
        (datasets keyed by HDF5 path, root attrs with JSON text left as stored).

    Raises:
        ValueError: (one line) not a readable database of this format version.
    """
    check_database(path)
    datasets: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: datasets.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset)
                     else None)
        attrs = dict(f.attrs)
    return datasets, attrs


def sizes(path: Path) -> tuple[int, int]:
    """(bytes of the file ``path``, bytes of its datasets uncompressed): what ``COMPRESSION`` saves."""
    raw = [0]
    with h5py.File(path, "r") as f:
        f.visititems(lambda _, item: raw.__setitem__(0, raw[0] + item.nbytes) if isinstance(item, h5py.Dataset)
                     else None)
    return Path(path).stat().st_size, raw[0]


def strain_dimension(path: Path) -> int:
    """Spatial dimension of the cells of database ``path`` [-]: 2 or 3, the width of its ``d_eps``.

    Raises:
        ValueError: (one line) not a readable database of this format version.
    """
    check_database(path)
    with h5py.File(path, "r") as f:
        return int(f["d_eps"].shape[1])


def bytes_per_sample(path: Path) -> float:
    """Bytes on disk [B] of one sample of database ``path``: its per-sample datasets' storage (the
    groups ``states``, ``schema`` and ``active_states`` left out) over the samples."""
    total = [0]
    with h5py.File(path, "r") as f:
        n = f["d_eps"].shape[0]

        def add(name: str, item: Any) -> None:
            if (isinstance(item, h5py.Dataset) and item.shape[:1] == (n,)
                    and not name.startswith(("states/", SCHEMA_GROUP + "/", ACTIVE_GROUP + "/"))):
                total[0] += item.id.get_storage_size()
        f.visititems(add)
    return total[0] / max(n, 1)


def read_attrs_of(path: Path) -> dict[str, dict[str, Any]]:
    """Attributes of every dataset and group of a database, keyed by HDF5 path."""
    out: dict[str, dict[str, Any]] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, item: out.__setitem__(name, dict(item.attrs)) if item.attrs else None)
    return out



def append_round(path: Path, samples: Mapping[str, np.ndarray], states: Mapping[str, np.ndarray],
                 record: Mapping[str, Any], clean: Callable[[Mapping[str, np.ndarray]], np.ndarray]) -> dict[str, Any]:
    """Append one active-learning round's ``samples`` and their start ``states`` to database
    ``path`` (rewritten atomically; docs/database_format.md, "Active-learning samples"); returns
    the round's record as stored in the root attr ``active_learning``.

    The per-sample datasets grow; the new samples get ``source_round`` = k (rounds so far + 1),
    ``path_id`` offset past every path of the file, ``state_id`` = their row in ``ACTIVE_GROUP``,
    and ``valid`` = the cleaning rules' mask when the file was cleaned (all True otherwise). The
    file is read whole into memory.

    Args:
        samples: the probes' arrays (``probing.compute_chunk``), first axis the sample.
        states: the probed start states: ``cell_size`` (n, dim) [m], ``free_position``
            (n, n_free) [m], ``shear_force`` (n, n_pairs) [N] (3D: (n, n_pairs, 3)), ``path_id``
            (n,) int64 numbered from 0 within the round.
        record: the rest of the round's entry (tests, seed, widths).

    Raises:
        ValueError: ``samples`` lacks a per-sample dataset of the file."""
    data, attrs = read_database(path)
    attrs_of = read_attrs_of(path)
    n_old = data["d_eps"].shape[0]
    rounds = json.loads(str(attrs.get("active_learning", "[]")))
    k = len(rounds) + 1
    per_sample = [name for name, value in data.items() if value.shape[:1] == (n_old,)
                  and not name.startswith(("states/", SCHEMA_GROUP + "/", ACTIVE_GROUP + "/"))]
    new = {name: np.asarray(value) for name, value in samples.items()}
    n_new = new["d_eps"].shape[0]
    path_base = int(data["path_id"].max(initial=-1)) + 1
    state_base = data[f"{ACTIVE_GROUP}/round"].size if f"{ACTIVE_GROUP}/round" in data else 0
    new["path_id"] = new["path_id"] + path_base
    new["state_id"] = new["state_id"] + state_base
    new["source_round"] = np.full(n_new, k, np.int64)
    data.setdefault("source_round", np.zeros(n_old, np.int64))
    if "valid" in data:
        new["valid"] = clean(new) if bool(attrs.get("cleaned", False)) else np.ones(n_new, bool)
    missing = sorted(set(per_sample) - set(new))
    if missing:
        raise ValueError(f"{path}: the new samples lack {', '.join(missing)}")
    for name in {*per_sample, "source_round"}:
        data[name] = np.concatenate([data[name], new[name].astype(data[name].dtype)])
    n_states = states["path_id"].size
    added = {**{name: states[name] for name in ("cell_size", "free_position", "shear_force")},
             "path_id": states["path_id"] + path_base, "round": np.full(n_states, k, np.int64)}
    for name, value in added.items():
        key = f"{ACTIVE_GROUP}/{name}"
        data[key] = np.concatenate([data[key], value]) if key in data else np.asarray(value)
    entry = {"round": k, "samples": int(n_new), "states": int(n_states), **record}
    rounds.append(entry)
    attrs.update(active_learning=json.dumps(rounds), n_samples=int(n_old + n_new),
                 n_active_samples=int(sum(r["samples"] for r in rounds)))
    if "n_valid" in attrs and "valid" in data:
        attrs["n_valid"] = int(np.count_nonzero(data["valid"]))
    attrs_of["source_round"] = {"units": "-", "description": "0: the generator; k: active-learning round k"}
    attrs_of[ACTIVE_GROUP] = {"description": "start states of the active-learning probes (state_id of samples "
                                             "with source_round > 0)"}
    write_database(path, data, attrs, attrs_of)
    return entry
