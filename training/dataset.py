"""Learning database (docs/database_format.md): loading, sample selection, split by path, normalisation.

Contract:

- ``load_database(path)`` reads a ``meso-hmodel-database`` HDF5 file and keeps the samples
  that are ``valid`` (not removed by the generator's cleaning step), pass the cleaning
  rules of ``warp_hcell.clean`` (re-applied, so an uncleaned file is cleaned the same
  way: converged, finite, alpha in [30, 90] deg and a closed contact before and after
  the probe) and have a non-zero probe (a zero probe has no rate to learn). It also drops
  snap-through jumps: probes whose dimensionless rate (see below) exceeds ``RATE_LIMIT``
  in any output, i.e. the cell jumped to another equilibrium branch within the probe (a
  discontinuity, not a rate; 2 of 3e5 samples of the DEM database, both from one state
  at alpha = 60 deg sliding with N2 = 0, that otherwise dominate the training MSE). Any
  unreadable, incomplete or wrong-format file raises ``DataError`` (one line).
- ``split_by_path`` makes disjoint training / validation / test sets of whole paths (never
  of samples): the test set holds every path of a few held-out ``alpha0`` values plus a
  fraction of the other paths; the remaining paths go 80 / 20 (by default) to training and
  validation.
- ``fit_normalisation`` computes z-score statistics on the training split only;
  ``tensors`` returns the z-scored features and z-scored rate targets that
  ``training.network.CellNet`` consumes.

Normalisation (spec section 11): lengths / D, forces / (kn D), angles in radians, with kn
and D = 2 r read from the file attributes. Targets are the increments of
``alpha, N1, N2, T1`` divided by the probe magnitude |d_eps| (see ``training.network``).
Sign convention: compression and contraction positive, as in the file.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from training.network import features
from warp_hcell.clean import pathological
from warp_hcell.database import FORMAT, FORMAT_VERSION, INPUT_FEATURES, OUTPUT_FEATURES, STATE_FEATURES


RATE_LIMIT = 10.0
"""Largest |rate| accepted [-]: d_alpha [rad] or dN1, dN2, dT1 [kn D] per unit |d_eps|.
Regular probes stay below ~1.6 (the H-cell's stiffness in these units)."""


class DataError(ValueError):
    """A database file that cannot be used; the message is one line naming the file."""


@dataclass(frozen=True)
class Database:
    """Selected samples of a learning database (first axis n_samples).

    Attributes:
        inputs: ``d_eps_n, d_eps_t, alpha_deg, N1, N2, T1, l1, l2``, shape (n, 8),
            compression positive [-, -, deg, N, N, N, m, m].
        outputs: POST-increment ``alpha_deg, N1, N2, T1``, shape (n, 4) [deg, N, N, N].
        path_id: exploration path of each sample, shape (n,).
        alpha0_deg: initial opening angle of the sample's path [deg], shape (n,).
        kn: normal contact stiffness [N/m]; kt_over_kn [-]; phi_g_deg [deg]; radius r [m].
        sha256: hex digest of the file bytes (the training-data hash of checkpoints).
        source: the file path; n_stored: samples in the file before selection;
        n_jumps: selected-but-dropped snap-through samples (|rate| > ``RATE_LIMIT``).
    """

    inputs: np.ndarray
    outputs: np.ndarray
    path_id: np.ndarray
    alpha0_deg: np.ndarray
    kn: float
    kt_over_kn: float
    phi_g_deg: float
    radius: float
    sha256: str
    source: str
    n_stored: int
    n_jumps: int

    @property
    def n_samples(self) -> int:
        """Number of selected samples."""
        return int(self.inputs.shape[0])

    @property
    def diameter(self) -> float:
        """Grain diameter D = 2 r [m]."""
        return 2.0 * self.radius

    @property
    def mu(self) -> float:
        """Friction coefficient tan(phi_g) [-]."""
        return math.tan(math.radians(self.phi_g_deg))


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def _attr_float(handle: h5py.File, name: str, path: Path) -> float:
    if name not in handle.attrs:
        raise DataError(f"{path}: root attribute {name!r} missing (not a complete learning database)")
    value = float(np.asarray(handle.attrs[name]))
    if not (math.isfinite(value) and value > 0.0):
        raise DataError(f"{path}: root attribute {name} = {value:g} must be finite and > 0")
    return value


def _dataset(handle: h5py.File, name: str, shape_tail: tuple[int, ...], path: Path) -> np.ndarray:
    if name not in handle or not isinstance(handle[name], h5py.Dataset):
        raise DataError(f"{path}: dataset {name!r} missing")
    data = handle[name][()]
    if data.shape[1:] != shape_tail:
        raise DataError(f"{path}: dataset {name!r} has shape {data.shape}, expected (n, {', '.join(map(str, shape_tail))})")
    return data


def _check_names(handle: h5py.File, name: str, expected: tuple[str, ...], path: Path) -> None:
    names = handle[name].attrs.get("feature_names")
    if names is not None:
        names = tuple(n.decode() if isinstance(n, bytes) else str(n) for n in names)
        if names != expected:
            raise DataError(f"{path}: {name} columns are {list(names)}, expected {list(expected)}")


def load_database(path: str | Path) -> Database:
    """Read a learning database and keep its usable samples (see module docstring).

    Raises:
        DataError: missing, unreadable, wrong-format or inconsistent file, or no usable sample.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such database file")
    try:
        handle = h5py.File(path, "r")
    except OSError:
        raise DataError(f"{path}: not a readable HDF5 file") from None
    with handle:
        fmt = handle.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT:
            raise DataError(f"{path}: format attribute is {fmt!r}, expected {FORMAT!r}")
        version = int(np.asarray(handle.attrs.get("format_version", -1)))
        if version != FORMAT_VERSION:
            raise DataError(f"{path}: format_version {version} is not supported (expected {FORMAT_VERSION})")
        kn = _attr_float(handle, "kn", path)
        kt = _attr_float(handle, "kt", path)
        radius = _attr_float(handle, "radius", path)
        phi_g_deg = float(np.asarray(handle.attrs.get("phi_g_deg", np.nan)))
        if not math.isfinite(phi_g_deg):
            raise DataError(f"{path}: root attribute 'phi_g_deg' missing")
        inputs = _dataset(handle, "inputs", (len(INPUT_FEATURES),), path).astype(np.float64)
        outputs = _dataset(handle, "outputs", (len(OUTPUT_FEATURES),), path).astype(np.float64)
        _check_names(handle, "inputs", INPUT_FEATURES, path)
        _check_names(handle, "outputs", OUTPUT_FEATURES, path)
        columns = {name: _dataset(handle, name, (len(STATE_FEATURES),), path) for name in ("pre_state", "post_state")}
        columns.update({name: _dataset(handle, name, (), path) for name in ("path_id", "alpha0_deg", "converged", "valid")})
    n_stored = inputs.shape[0]
    for name, data in (("outputs", outputs), *columns.items()):
        if data.shape[0] != n_stored:
            raise DataError(f"{path}: dataset {name!r} has {data.shape[0]} samples, inputs has {n_stored}")
    removed = pathological({"inputs": inputs, "outputs": outputs, **columns})
    keep = (
        columns["valid"].astype(bool)
        & ~np.logical_or.reduce(list(removed.values()))
        & np.any(inputs[:, :2] != 0.0, axis=1)
    )
    jumps = np.zeros_like(keep)
    jumps[keep] = np.abs(rates(inputs[keep], outputs[keep], kn, 2.0 * radius)).max(axis=1) > RATE_LIMIT
    keep &= ~jumps
    if not keep.any():
        raise DataError(f"{path}: no valid, converged sample with a non-zero probe among {n_stored}")
    return Database(
        inputs=inputs[keep],
        outputs=outputs[keep],
        path_id=columns["path_id"].astype(np.int64)[keep],
        alpha0_deg=columns["alpha0_deg"].astype(np.float64)[keep],
        kn=kn,
        kt_over_kn=kt / kn,
        phi_g_deg=phi_g_deg,
        radius=radius,
        sha256=file_sha256(path),
        source=str(path),
        n_stored=int(n_stored),
        n_jumps=int(np.count_nonzero(jumps)),
    )


@dataclass(frozen=True)
class Split:
    """Disjoint sample indices (into ``Database`` arrays) of whole paths.

    Attributes:
        train, val, test: int64 sample indices, each sorted.
        test_alpha0_deg: alpha0 values [deg] whose paths are all in ``test``.
    """

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray
    test_alpha0_deg: tuple[float, ...]


def split_by_path(
    db: Database,
    *,
    val_fraction: float,
    test_path_fraction: float,
    n_test_alpha0: int,
    seed: int,
) -> Split:
    """Split ``db`` by path into training, validation and test sets (seeded, deterministic).

    Args:
        db: selected samples.
        val_fraction: fraction of the non-test paths used for validation [-], in (0, 1).
        test_path_fraction: fraction of the paths (after removing held-out alpha0 values)
            moved to the test set [-], in [0, 1).
        n_test_alpha0: number of distinct alpha0 values held out entirely; chosen at random
            among the interior values (never the smallest or largest, which would make the
            test an extrapolation). Fewer if fewer interior values exist.
        seed: seed of the random choices.
    """
    if not (0.0 < val_fraction < 1.0) or not (0.0 <= test_path_fraction < 1.0):
        raise ValueError(f"val_fraction = {val_fraction:g} must be in (0, 1), test_path_fraction = {test_path_fraction:g} in [0, 1)")
    rng = np.random.default_rng(seed)
    paths, first = np.unique(db.path_id, return_index=True)
    path_alpha0 = db.alpha0_deg[first]
    distinct = np.unique(path_alpha0)
    interior = distinct[1:-1]
    held = np.sort(rng.choice(interior, size=min(n_test_alpha0, interior.size), replace=False))
    test_paths = paths[np.isin(path_alpha0, held)]
    rest = rng.permutation(paths[~np.isin(path_alpha0, held)])
    n_test = int(round(test_path_fraction * rest.size))
    test_paths = np.concatenate([test_paths, rest[:n_test]])
    rest = rest[n_test:]
    n_val = max(1, int(round(val_fraction * rest.size)))
    if rest.size - n_val < 1:
        raise DataError(f"{db.source}: {paths.size} paths are too few to split into training, validation and test sets")
    val_paths, train_paths = rest[:n_val], rest[n_val:]
    index = lambda chosen: np.flatnonzero(np.isin(db.path_id, chosen))  # noqa: E731
    return Split(index(train_paths), index(val_paths), index(test_paths), tuple(float(a) for a in held))


@dataclass(frozen=True)
class Normalisation:
    """z-score statistics (from the training split) in dimensionless units.

    Attributes:
        feature_mean, feature_std: of the dimensionless ``training.network.features``,
            shape (N_FEATURES,).
        rate_mean, rate_std: of the rates (increment / |d_eps|) of ``alpha [rad], N1, N2, T1 [kn D]``, shape (4,).
    """

    feature_mean: np.ndarray
    feature_std: np.ndarray
    rate_mean: np.ndarray
    rate_std: np.ndarray


def rates(inputs: np.ndarray, outputs: np.ndarray, kn: float, diameter: float) -> np.ndarray:
    """Dimensionless rates (n, 4): increments of alpha [rad] and N1, N2, T1 [kn D] over |d_eps|.

    Args:
        inputs: (n, 8) database inputs, non-zero probes; outputs: (n, 4) database outputs.
        kn: normal stiffness [N/m]; diameter: grain diameter D [m].
    """
    increment = outputs - inputs[:, 2:6]
    increment[:, 0] = np.radians(increment[:, 0])
    increment[:, 1:] /= kn * diameter
    return increment / np.hypot(inputs[:, 0], inputs[:, 1])[:, None]


def dimensionless(db: Database, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Un-z-scored features (n, N_FEATURES) and rates (n, 4) of the samples ``index``."""
    raw, _ = features(torch.from_numpy(db.inputs[index]), db.kn, db.diameter, db.mu)
    return raw.numpy(), rates(db.inputs[index], db.outputs[index], db.kn, db.diameter)


def fit_normalisation(db: Database, train: np.ndarray) -> Normalisation:
    """z-score statistics of the training samples; a constant column gets std 1."""
    raw, rate = dimensionless(db, train)
    std = lambda x: np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0)  # noqa: E731
    return Normalisation(raw.mean(axis=0), std(raw), rate.mean(axis=0), std(rate))


def tensors(db: Database, index: np.ndarray, norm: Normalisation) -> tuple[torch.Tensor, torch.Tensor]:
    """z-scored features (n, N_FEATURES) and z-scored rate targets (n, 4), float64 tensors."""
    raw, rate = dimensionless(db, index)
    return (
        torch.from_numpy((raw - norm.feature_mean) / norm.feature_std),
        torch.from_numpy((rate - norm.rate_mean) / norm.rate_std),
    )
