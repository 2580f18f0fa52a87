"""Out-of-distribution distance of cell states from a model's learning database.

A cell state (cell size, free-DOF coordinates, tangential spring forces) is mapped to the
network's own input features without the probe direction (``state_features``: the features of
``training.network.features_and_contacts`` after their first two columns, z-scored with the
network's training statistics, so one unit is one standard deviation of that feature in the
training data). ``OodIndex`` holds a subsample of database states in that space (nearest
neighbours by brute force for a few distinct states, else a ``scipy.spatial.cKDTree`` built on
first use); a state whose Euclidean distance to its nearest indexed state exceeds
``threshold`` is out of distribution.

Threshold: the ``QUANTILE`` (99.9 %) quantile of the nearest-neighbour distances of held-out
database states (the test split, paths the index did not draw from) to the index. By
construction about 0.1 % of states like the database's are flagged, so a run whose fraction of
flagged cell-increments is much larger (``WARN_FRACTION``) visits states the network was not
trained near (docs/certificate.md).

File format (``index_path(model)``: ``<model stem>_ood.npz`` beside the ``.pt``, numpy npz):
``points`` float64 (n_points, n_state_features), the indexed z-scored states; ``threshold``
float64 scalar (z units); ``quantile`` float64 scalar; ``n_database`` int64 scalar (states it was
drawn from); ``database_sha256`` str scalar; ``n_features`` int64 scalar (columns of
``points``); ``normalisation_sha256`` str scalar (``normalisation_digest`` of the model the
points were z-scored with: an index is only read with that model).

``python -m training.ood --model M.pt --data DB.h5`` (the command ``training.ood_command``) builds
the index of a trained model from its database (the split of its JSON's ``config``;
``training.fitting.train_and_save`` writes it at the end of training).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import hashlib
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from training.dataset import Database
    from training.network import MesoNet

N_POINTS = 2000
"""Database states drawn into the index."""
QUANTILE = 0.999
"""Quantile of the held-out states' nearest-neighbour distances that sets the threshold [-]."""
BRUTE_FORCE_ROWS = 64
"""Distinct rows up to which ``OodIndex.distance`` searches by brute force (no tree, no import: the
first check of a run, all cells at one start state, is one row); more go through a k-d tree."""
WARN_FRACTION = 0.05
"""Fraction of checked cell-increments beyond the threshold above which a run is warned [-]."""
PROBE_COLUMNS = 2
"""Leading feature columns that describe the probe direction of a planar cell, not the state
(left out); a spatial cell has three (``probe_columns``)."""


def probe_columns(net: Any) -> int:
    """Leading feature columns of ``net`` (a ``MesoNet`` or ``training.fast_model.NetArrays``) that describe
    the probe direction: one per local axis."""
    return net.schema.dim


class OodError(ValueError):
    """An index file that cannot be used with its model (one line naming the file)."""


def index_path(model: str | Path) -> Path:
    """The index file that goes with model ``model`` (``<stem>_ood.npz`` beside it)."""
    model = Path(model)
    return model.with_name(f"{model.stem}_ood.npz")


def normalisation_digest(net: Any) -> str:
    """sha256 of the network's feature normalisation (mean then std, float64 bytes); ``net``: a ``MesoNet``
    or ``training.fast_model.NetArrays``."""
    digest = hashlib.sha256()
    for name in ("feature_mean", "feature_std"):
        values = getattr(net, name)
        values = values.detach().cpu().numpy() if hasattr(values, "detach") else np.asarray(values)
        digest.update(values.astype(np.float64).tobytes())
    return digest.hexdigest()


def state_features(net: MesoNet, cell_size: np.ndarray, free_position: np.ndarray,
                   shear_force: np.ndarray) -> np.ndarray:
    """z-scored state features of cells, shape (n, n_state_features) [-].

    Args:
        cell_size: (n, dim) [m]; free_position: (n, n_free) [m]; shear_force: (n, n_pairs)
            (3D: (n, n_pairs, 3)) [N] (DEM convention), all in the network's schema order.
    """
    import torch  # noqa: PLC0415 (the network's own features; a compiled run passes them instead)

    t = [torch.as_tensor(np.asarray(a, dtype=np.float64)) for a in (cell_size, free_position, shear_force)]
    device = net.feature_mean.device
    t = [a.to(device) for a in t]
    with torch.inference_mode():
        probe = torch.zeros(t[0].shape[0], net.schema.dim, dtype=torch.float64, device=device)
        feats = net.raw_features(*t, probe)[0]
        z = (feats - net.feature_mean) / net.feature_std
    return np.ascontiguousarray(z[:, probe_columns(net):].cpu().numpy())


def database_features(net: MesoNet, db: Database, index: np.ndarray) -> np.ndarray:
    """``state_features`` of the states before the probes of samples ``index``."""
    from training.dataset import STATE_FIELDS  # noqa: PLC0415

    return state_features(net, *(db.before[k][index] for k in STATE_FIELDS))


@dataclass
class OodIndex:
    """Indexed database states and the out-of-distribution threshold (module docstring)."""

    points: np.ndarray
    threshold: float
    quantile: float
    n_database: int
    database_sha256: str
    normalisation_sha256: str

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self._norm2 = np.einsum("ij,ij->i", self.points, self.points)
        self._tree = None

    def _exact(self, rows: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Euclidean distances (m, k) of ``rows`` (m, d) to the indexed points ``index`` (m, k), from differences."""
        diff = rows[:, None, :] - self.points[index]
        return np.sqrt(np.einsum("mkd,mkd->mk", diff, diff))

    def _brute_force(self, query: np.ndarray) -> np.ndarray:
        """Nearest distances of the rows of ``query``: the nearest point by |a|^2 - 2 a.b + |b|^2, its exact
        distance, and exact distances to every point whose estimate is within the estimate's rounding bound."""
        q2 = np.einsum("ij,ij->i", query, query)
        estimate = q2[:, None] - 2.0 * (query @ self.points.T) + self._norm2[None, :]
        best = self._exact(query, estimate.argmin(axis=1)[:, None])[:, 0]
        bound = 1e-12 * query.shape[1] * (q2 + self._norm2.max())
        close = estimate <= (best * best + 2.0 * bound)[:, None]
        for i in np.flatnonzero(np.count_nonzero(close, axis=1) > 1):
            best[i] = self._exact(query[i:i + 1], np.flatnonzero(close[i])[None, :]).min()
        return best

    def distance(self, features: np.ndarray) -> np.ndarray:
        """Nearest-neighbour distance [z units] of each row of ``features`` (n, n_state_features), shape (n,).

        Rows equal bit for bit are queried once (cells of one start state share their distance): up to
        ``BRUTE_FORCE_ROWS`` distinct rows by brute force (``_brute_force``; no import), more through a
        ``scipy.spatial.cKDTree`` built on first use. Both are exact to rounding."""
        rows = np.ascontiguousarray(features, dtype=np.float64)
        keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        query = rows[first]
        if query.shape[0] <= BRUTE_FORCE_ROWS:
            return self._brute_force(query)[inverse.ravel()]
        if self._tree is None:
            from scipy.spatial import cKDTree  # noqa: PLC0415 (~0.5 s to import: only where many rows are queried)

            self._tree = cKDTree(self.points)
        return self._tree.query(query, k=1)[0][inverse.ravel()]

    def outside(self, features: np.ndarray) -> np.ndarray:
        """True where a state lies beyond ``threshold``, shape (n,) bool."""
        return self.distance(features) > self.threshold

    def save(self, path: str | Path) -> Path:
        """Write the index file (format: module docstring); returns the path."""
        path = Path(path)
        with open(path, "wb") as f:
            np.savez(f, points=self.points, threshold=np.float64(self.threshold), quantile=np.float64(self.quantile),
                     n_database=np.int64(self.n_database), database_sha256=np.str_(self.database_sha256),
                     n_features=np.int64(self.points.shape[1]),
                     normalisation_sha256=np.str_(self.normalisation_sha256))
        return path


def build_index(net: MesoNet, db: Database, indexed: np.ndarray, held_out: np.ndarray, *,
                n_points: int = N_POINTS, quantile: float = QUANTILE, seed: int = 0) -> OodIndex:
    """Index ``n_points`` unperturbed states drawn from samples ``indexed``; threshold from ``held_out``.

    Perturbed samples (states the DEM relaxes, not states of a path) are left out of both.
    """
    rng = np.random.default_rng(seed)
    indexed = indexed[~db.perturbed[indexed]]
    held_out = held_out[~db.perturbed[held_out]]
    if indexed.size == 0 or held_out.size == 0:
        raise OodError(f"{db.source}: no unperturbed state to index or to set the threshold from")
    chosen = np.sort(rng.choice(indexed, size=min(n_points, indexed.size), replace=False))
    index = OodIndex(database_features(net, db, chosen), 0.0, quantile, int(db.n_samples), db.sha256,
                     normalisation_digest(net))
    distance = index.distance(database_features(net, db, held_out))
    index.threshold = float(np.quantile(distance, quantile))
    return index


def load_index(path: str | Path, net: Any) -> OodIndex:
    """Read an index file written by ``OodIndex.save`` for ``net`` (a ``MesoNet`` or
    ``training.fast_model.NetArrays``); ``OodError`` (one line) if
    unreadable or built with another network's normalisation."""
    path = Path(path)
    keys = ("points", "threshold", "quantile", "n_database", "database_sha256", "n_features", "normalisation_sha256")
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in keys}
    except (OSError, KeyError, ValueError):
        raise OodError(f"{path}: not a readable out-of-distribution index file") from None
    if str(data["normalisation_sha256"]) != normalisation_digest(net) or data["points"].ndim != 2:
        raise OodError(f"{path}: an index built for another model (its normalisation differs); rebuild it: "
                       f"python -m training.ood --model MODEL --data DATABASE")
    return OodIndex(np.asarray(data["points"], dtype=np.float64), float(data["threshold"]), float(data["quantile"]),
                    int(data["n_database"]), str(data["database_sha256"]), str(data["normalisation_sha256"]))


def index_for_model(net: MesoNet, config: dict, db: Database) -> OodIndex:
    """The index of a model trained on ``db`` with training ``config`` (its split: indexed
    states from the training paths, the threshold from the test paths)."""
    from training.dataset import split_by_path  # noqa: PLC0415

    split = split_by_path(db, val_fraction=config["val_fraction"], test_fraction=config["test_fraction"],
                          seed=config["seed"], by_round=config.get("init_from") is not None)
    return build_index(net, db, split.train, split.test, seed=config["seed"])


if __name__ == "__main__":  # python -m training.ood runs the command module training.ood_command as its script
    import runpy  # noqa: PLC0415

    runpy.run_module("training.ood_command", run_name="__main__")
