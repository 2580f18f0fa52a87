"""Generic learning database (format version 2, docs/database_format.md): loading, selection, split, normalisation.

Contract:

- ``load_database(path)`` reads a ``meso-hmodel-database`` HDF5 file of format version 2
  (the generic DEM state before and after each probe) and keeps the converged samples
  (and, in a cleaned file, the ``valid`` ones).
  Mechanism (stress-free) and perturbed (unbalanced) samples are kept: the network must
  learn them. Snap-through probes, whose free DOFs moved more than ``RATE_LIMIT`` D per unit
  of (probe magnitude + unbalanced force / (kn D)), are dropped and counted (a jump to
  another equilibrium branch is a discontinuity, not a rate). Any unreadable, incomplete or
  wrong-format file raises ``DataError`` (one line).
- ``split_by_path`` makes disjoint training / validation / test sets of whole paths.
- ``fit_normalisation`` computes the feature and rate statistics on the training split;
  ``tensors`` returns the raw features, probe magnitudes, unbalanced forces and targets that
  ``training.network.MesoNet`` consumes.

Nothing here knows a particular mesostructure: the schema group of the file gives the
topology. Sign convention: compression positive, as in the file.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from training.cell_physics import CellSchema
from training.network import features
from warp_hcell.core.dimension import dimension
from warp_hcell.core.provenance import file_sha256

FORMAT = "meso-hmodel-database"
"""Root attr ``format`` of a learning database."""
FORMAT_VERSION = 2
"""Supported root attr ``format_version`` (the generic database)."""
RATE_LIMIT = 50.0
"""Largest free-DOF displacement accepted, in D per unit of ``(|d_eps| + |F|max / (kn D))`` [-]."""
STATE_FIELDS = ("cell_size", "free_position", "shear_force")
"""Per-sample datasets of the groups ``before``/``after`` that the network reads."""
SCHEMA_FIELDS = ("free_dofs", "pairs", "radius", "reference_position", "reference_cell_size", "driven", "outer")
"""Datasets of the group ``schema``."""


class DataError(ValueError):
    """A database file that cannot be used; the message is one line naming the file."""


@dataclass(frozen=True)
class Database:
    """Selected samples of a generic learning database (first axis n_samples).

    Attributes:
        before: ``cell_size`` (n, dim) [m], ``free_position`` (n, n_free) [m], ``shear_force``
            (n, n_pairs) [N] (3D: (n, n_pairs, 3)) before the probe.
        after_free_position: free-DOF coordinates after the probe [m], (n, n_free).
        after_contact, before_contact: contact flags, bool (n, n_pairs).
        d_eps: probes (n, dim) [-], compression positive.
        perturbed, mechanism: bool (n,); path_id, source_round (0: the generator), row: int (n,).
        schema_arrays, schema: the ``schema`` group (numpy) and its ``CellSchema``.
        mesostructure, mesostructure_sha256: JSON description in the file, its hash.
        start_mesostructures: descriptions of the exploration's start cells.
        kn [N/m], kt_over_kn [-], phi_g_deg [deg], contact_tolerance [-]: file attributes.
        sha256, source: hex digest of the file bytes, its path.
        n_stored: samples in the file.
        n_unconverged, n_jumps: samples dropped as unconverged, as jumps (a free-DOF
            displacement above ``RATE_LIMIT`` times the sample's scale)."""

    before: dict
    after_free_position: np.ndarray
    after_contact: np.ndarray
    before_contact: np.ndarray
    d_eps: np.ndarray
    perturbed: np.ndarray
    mechanism: np.ndarray
    path_id: np.ndarray
    source_round: np.ndarray
    row: np.ndarray
    schema_arrays: dict
    schema: CellSchema
    mesostructure: str
    mesostructure_sha256: str
    start_mesostructures: tuple[str, ...]
    kn: float
    kt_over_kn: float
    phi_g_deg: float
    contact_tolerance: float
    sha256: str
    source: str
    n_stored: int
    n_unconverged: int
    n_jumps: int

    @property
    def n_samples(self) -> int:
        """Number of selected samples."""
        return int(self.d_eps.shape[0])


def schema_from_arrays(arrays: dict, *, kn: float, kt_over_kn: float, phi_g_deg: float,
                       contact_tolerance: float) -> CellSchema:
    """``CellSchema`` of a database/checkpoint ``schema`` dict and a contact law."""
    return CellSchema.from_arrays(
        radius=arrays["radius"], reference_position=arrays["reference_position"],
        reference_cell_size=arrays["reference_cell_size"], driven=arrays["driven"], pairs=arrays["pairs"],
        outer=arrays["outer"], kn=kn, kt=kt_over_kn * kn, mu=math.tan(math.radians(phi_g_deg)),
        contact_tolerance=contact_tolerance)


def load_database(path: str | Path) -> Database:
    """Read and select the samples of a generic database (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such database file")
    try:
        handle = h5py.File(path, "r")
    except OSError:
        raise DataError(f"{path}: not a readable HDF5 file") from None
    with handle:
        attrs = dict(handle.attrs)
        if attrs.get("format") != FORMAT:
            raise DataError(f"{path}: not a {FORMAT} file")
        if int(attrs.get("format_version", -1)) != FORMAT_VERSION:
            raise DataError(f"{path}: format_version {attrs.get('format_version')!r} is not the generic database "
                            f"(version {FORMAT_VERSION}); regenerate it with python -m warp_hcell.generate")
        try:
            schema_arrays = {k: np.array(handle["schema"][k]) for k in SCHEMA_FIELDS}
            before = {k: np.array(handle["before"][k], dtype=np.float64) for k in STATE_FIELDS}
            after_free = np.array(handle["after/free_position"], dtype=np.float64)
            after_contact = np.array(handle["after/contact"]) == 1
            before_contact = np.array(handle["before/contact"]) == 1
            d_eps = np.array(handle["d_eps"], dtype=np.float64)
            flags = {k: np.array(handle[k], dtype=bool) for k in ("perturbed", "mechanism", "converged")}
            valid = np.array(handle["valid"], dtype=bool) if "valid" in handle else np.ones(d_eps.shape[0], bool)
            path_id = np.array(handle["path_id"], dtype=np.int64)
            source_round = (np.array(handle["source_round"], dtype=np.int64) if "source_round" in handle
                            else np.zeros(d_eps.shape[0], np.int64))
            kn = float(attrs["kn"])
            kt = float(attrs["kt"])
            phi_g_deg = float(attrs["phi_g_deg"])
            settings = json.loads(str(attrs.get("dem_settings", "{}")))
            tolerance = float(settings.get("contact_tolerance", 1e-9))
            text = str(attrs["mesostructure"])
            digest = str(attrs["mesostructure_sha256"])
            starts = tuple(json.loads(str(attrs["start_mesostructures"]))) if "start_mesostructures" in attrs else (text,)
        except KeyError as exc:
            raise DataError(f"{path}: missing {exc.args[0]!r} (incomplete generic database)") from None
    n = d_eps.shape[0]
    n_free = schema_arrays["free_dofs"].shape[0]
    dim = schema_arrays["driven"].shape[1]
    n_pairs = schema_arrays["pairs"].shape[0]
    stored = {"before/" + name: value for name, value in before.items()} | {"d_eps": d_eps}
    shapes = {"before/cell_size": (n, dim), "before/free_position": (n, n_free),
              "before/shear_force": (n, n_pairs, *dimension(dim).spring_shape), "d_eps": (n, dim)}
    for name, shape in shapes.items():
        if stored[name].shape != shape:
            raise DataError(f"{path}: {name} has shape {stored[name].shape}, expected {shape}")
    schema = schema_from_arrays(schema_arrays, kn=kn, kt_over_kn=kt / kn, phi_g_deg=phi_g_deg,
                                contact_tolerance=tolerance)
    keep = valid & flags["converged"] & np.all(np.isfinite(after_free), axis=1)
    _, m, unbalanced = features(schema, torch.zeros(schema.n_pairs, dtype=torch.bool),
                                *(torch.from_numpy(before[k]) for k in STATE_FIELDS), torch.from_numpy(d_eps))
    scale = schema.diameter * (m[:, 0].numpy() + np.abs(unbalanced.numpy()).max(axis=1, initial=0.0) / (kn * schema.diameter))
    moved = np.abs(after_free - before["free_position"]).max(axis=1, initial=0.0)
    jump = keep & (moved > RATE_LIMIT * scale)
    keep &= ~jump
    return Database(
        before={k: v[keep] for k, v in before.items()}, after_free_position=after_free[keep],
        after_contact=after_contact[keep], before_contact=before_contact[keep], d_eps=d_eps[keep],
        perturbed=flags["perturbed"][keep], mechanism=flags["mechanism"][keep], path_id=path_id[keep],
        source_round=source_round[keep], row=np.flatnonzero(keep),
        schema_arrays=schema_arrays, schema=schema, mesostructure=text, mesostructure_sha256=digest,
        start_mesostructures=starts, kn=kn,
        kt_over_kn=kt / kn, phi_g_deg=phi_g_deg, contact_tolerance=tolerance, sha256=file_sha256(path),
        source=str(path), n_stored=n, n_unconverged=int(np.count_nonzero(~flags["converged"])),
        n_jumps=int(np.count_nonzero(jump)))


@dataclass(frozen=True)
class Split:
    """Sample indices of the training, validation and test sets (disjoint by path)."""

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray


def split_by_path(db: Database, *, val_fraction: float, test_fraction: float, seed: int,
                  by_round: bool = False) -> Split:
    """Split whole paths (never samples): ``test_fraction`` of the paths to test, then
    ``val_fraction`` of the rest to validation, the remainder to training.

    ``by_round``: the paths of each ``source_round`` are split on their own (round 0 as the
    whole file is split without it, round k with the seed [seed, k]; a round with too few paths
    for a test or validation path goes to training), so appending a round moves no earlier
    path to another set: a warm start (``training.train``, ``TrainConfig.init_from``) then never
    validates on paths its start model was trained on. Without ``by_round`` all paths are
    drawn in one permutation.
    """
    if not by_round:
        test, val = _held_out(np.unique(db.path_id), val_fraction, test_fraction, np.random.default_rng(seed), db.source)
    else:
        parts = [_held_out(np.unique(db.path_id[db.source_round == k]), val_fraction, test_fraction,
                           np.random.default_rng(seed if k == 0 else [seed, int(k)]), db.source, strict=k == 0)
                 for k in np.unique(db.source_round)]
        test, val = (np.concatenate([part[i] for part in parts]) for i in (0, 1))
    in_test, in_val = np.isin(db.path_id, test), np.isin(db.path_id, val)
    return Split(np.flatnonzero(~in_test & ~in_val), np.flatnonzero(in_val), np.flatnonzero(in_test))


def _held_out(paths: np.ndarray, val_fraction: float, test_fraction: float, rng: np.random.Generator, source: str,
              strict: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(test, validation) path ids drawn from ``paths``; ``strict``: DataError where no path is
    left for training, validation or (a ``test_fraction`` above 0) testing."""
    order = rng.permutation(paths)
    n_test = int(round(test_fraction * paths.size))
    n_val = int(round(val_fraction * (paths.size - n_test)))
    if paths.size - n_test - n_val < 1 or n_val < 1 or (test_fraction > 0.0 and n_test < 1):
        if strict:
            raise DataError(f"{source}: {paths.size} paths are too few to split into training, validation and test")
        return order[:0], order[:0]
    return order[:n_test], order[n_test:n_test + n_val]


@dataclass(frozen=True)
class Tensors:
    """Network inputs and targets of a set of samples.

    Attributes:
        features: raw features (n, n_features).
        magnitude: probe magnitude ``|d_eps|`` (n, 1).
        unbalanced: unbalanced force F on the free DOFs (n, n_free) [N].
        target: true free-DOF displacement [m], (n, n_free).
        scale: per-sample length ``D (|d_eps| + |F|max / (kn D))`` [m], (n, 1), the unit of the loss.
    """

    features: torch.Tensor
    magnitude: torch.Tensor
    unbalanced: torch.Tensor
    target: torch.Tensor
    scale: torch.Tensor


def active_pairs(db: Database, index: np.ndarray) -> np.ndarray:
    """Pairs in contact before or after some probe of ``index``, bool (n_pairs,)."""
    return (db.before_contact[index] | db.after_contact[index]).any(axis=0)


def tensors(db: Database, index: np.ndarray, active: np.ndarray, load_features: bool = False) -> Tensors:
    """Features and targets of samples ``index`` for a network seeing pairs ``active`` (and, with
    ``load_features``, their load fractions: ``training.network``)."""
    state = (torch.from_numpy(db.before[k][index]) for k in STATE_FIELDS)
    feats, m, unbalanced = features(db.schema, torch.from_numpy(active), *state, torch.from_numpy(db.d_eps[index]),
                                    load_features)
    diameter = db.schema.diameter
    target = torch.from_numpy(db.after_free_position[index] - db.before["free_position"][index])
    scale = diameter * (m + unbalanced.abs().amax(dim=1, keepdim=True) / (db.kn * diameter)) + 1e-12 * diameter
    return Tensors(feats, m, unbalanced, target, scale)


RATE_STD_DEGENERATE = 1e-2
"""A free DOF whose rate standard deviation over the unperturbed samples is at most this fraction
of the largest free DOF's [-] is degenerate: it moves by round-off only under the cell strain
(e.g. a fine grain held on the cell axis by symmetry: 3.5e-5 - 7e-4 of the largest in the
ten-sphere cell with a centred fine grain) and gets a standard deviation of 1, as a rate that is
exactly constant does; its own spread would weigh its errors by the inverse square of round-off
in the loss."""


@dataclass(frozen=True)
class Normalisation:
    """Training statistics: features (n_features,), rates (n_free,) [D per unit strain], and the
    free DOFs whose rate was degenerate (``RATE_STD_DEGENERATE``: standard deviation set to 1)."""

    feature_mean: np.ndarray
    feature_std: np.ndarray
    rate_mean: np.ndarray
    rate_std: np.ndarray
    degenerate_rates: tuple[int, ...] = ()


def fit_normalisation(db: Database, data: Tensors, index: np.ndarray) -> Normalisation:
    """z-score statistics of ``data`` (the training tensors of samples ``index``).

    Rates ``d_free / (D |d_eps|)`` come from the unperturbed samples with a non-zero probe.
    Constant features, and rates that are constant or degenerate (``RATE_STD_DEGENERATE``), get a
    standard deviation of 1.
    """
    feats = data.features.numpy()
    mean, std = feats.mean(axis=0), feats.std(axis=0)
    clean = ~db.perturbed[index] & (data.magnitude[:, 0].numpy() > 0)
    rate = data.target.numpy()[clean] / (db.schema.diameter * data.magnitude.numpy()[clean])
    if rate.shape[0] == 0:
        raise DataError(f"{db.source}: no unperturbed sample with a non-zero probe in the training split")
    r_mean, r_std = rate.mean(axis=0), rate.std(axis=0)
    degenerate = r_std <= max(1e-12, RATE_STD_DEGENERATE * float(r_std.max()))
    return Normalisation(mean, np.where(std > 1e-12, std, 1.0), r_mean, np.where(degenerate, 1.0, r_std),
                         tuple(int(k) for k in np.flatnonzero(degenerate & (r_std > 1e-12))))
