"""A trained meso-ANN as numpy arrays, read without torch: what compiled inference needs.

``read_state_dict(path)`` reads the tensors of a model's ``.pt`` file (the zip archive that
``torch.save`` writes of a ``state_dict``) with ``zipfile`` and a restricted unpickler: only
tensor rebuilds, storage types and ``OrderedDict`` are accepted, so, as with
``torch.load(weights_only=True)``, no pickled code runs. The file is the same one that
``training.checkpoint.load_checkpoint`` reads and that the certificate's ``model_sha256`` names.

``NetArrays`` holds what ``training.inference.FastAdvance`` and the cell's start states take:
the schema (``SchemaArrays``: numpy, float64/int64), the active pairs, the z-score statistics and
the layers' weights; ``net_arrays(path, metadata)`` builds it from a model file and its JSON,
``arrays_of_net(net)`` from a ``training.network.MesoNet``. Both give bit-identical arrays.

``contacts``, ``pair_forces`` and ``love_weber`` are the contact law of ``training.cell_physics`` on
numpy arrays (cells first), for a cell's response and observables (V_cell:
``warp_hcell.mesostructures.mesostructure.cell_measure``).

The network's constants (``ACTIVATION``, ``GAP_CLIP``, ``COMPLIANCE_SCALE``,
``RELAXATION_RAMP``) live here so that inference reads them without torch; ``training.network``
uses the same objects.
"""

from __future__ import annotations

import io
import math
import pickle
import zipfile
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import numpy as np

from warp_hcell.core.dimension import dimension

ACTIVATION = "tanh"
"""Hidden activation (the output layer is linear)."""
GAP_CLIP = 0.05
"""Gaps larger than this fraction of D look alike to the network [-]."""
COMPLIANCE_SCALE = 0.5
"""Initial and reference compliance C [1/kn]: a free grain between two contacts."""
RELAXATION_RAMP = 1e-7
"""Probe magnitude [-] below which ``advance`` scales the relaxation term by ``|d_eps| / RELAXATION_RAMP``,
so that a zero increment leaves a state unchanged (stress control brackets the increment
from zero); 100 times below the smallest probe of the databases, so never active in a run."""

_STORAGES = {"DoubleStorage": np.float64, "FloatStorage": np.float32, "HalfStorage": np.float16,
             "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8,
             "ByteStorage": np.uint8, "BoolStorage": np.bool_}
"""torch storage types (as pickled in a ``.pt`` archive) -> numpy dtype."""


class StateDictError(ValueError):
    """A ``.pt`` file that is not a readable ``state_dict`` of plain tensors."""


class _Storage(NamedTuple):
    dtype: Any


def _rebuild_tensor(storage, offset, size, stride, *_):
    """numpy copy of the tensor of ``size`` and ``stride`` (elements) at ``offset`` in ``storage``."""
    if len(size) == 0:
        return np.array(storage[offset])
    itemsize = storage.dtype.itemsize
    view = np.lib.stride_tricks.as_strided(storage[offset:], shape=tuple(size),
                                           strides=tuple(s * itemsize for s in stride))
    return np.array(view)


def read_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """The tensors of the ``state_dict`` saved at ``path`` by ``torch.save``, as numpy arrays (copies).

    Raises ``StateDictError`` (one line) for a file that is not such an archive or holds other
    objects than tensors (nothing it holds is executed)."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            pickled = next((n for n in names if n.endswith("data.pkl") and n.count("/") == 1), None)
            if pickled is None:
                raise StateDictError(f"{path}: not a torch state_dict archive")
            root = pickled[:-len("data.pkl")]
            order = archive.read(root + "byteorder").decode().strip() if root + "byteorder" in names else "little"
            endian = "<" if order == "little" else ">"

            class _Unpickler(pickle.Unpickler):
                def find_class(self, module, name):
                    if module == "torch._utils" and name == "_rebuild_tensor_v2":
                        return _rebuild_tensor
                    if module == "torch" and name in _STORAGES:
                        return _Storage(np.dtype(_STORAGES[name]).newbyteorder(endian))
                    if module == "collections" and name == "OrderedDict":
                        return OrderedDict
                    raise StateDictError(f"{path}: holds {module}.{name}, not only tensors")

                def persistent_load(self, pid):
                    kind, storage, key, _location, numel = pid
                    if kind != "storage" or not isinstance(storage, _Storage):
                        raise StateDictError(f"{path}: unexpected persistent record {kind!r}")
                    raw = np.frombuffer(archive.read(f"{root}data/{key}"), dtype=storage.dtype)
                    return raw[:numel].astype(storage.dtype.newbyteorder("="), copy=False)

            state = _Unpickler(io.BytesIO(archive.read(pickled))).load()
    except (OSError, zipfile.BadZipFile, KeyError, pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        if isinstance(exc, StateDictError):
            raise
        raise StateDictError(f"{path}: not a readable torch state_dict") from None
    if not isinstance(state, dict) or not all(isinstance(v, np.ndarray) for v in state.values()):
        raise StateDictError(f"{path}: not a state_dict of tensors")
    return dict(state)


@dataclass(frozen=True)
class SchemaArrays:
    """A mesostructure's schema as numpy arrays (``training.cell_physics.CellSchema`` without torch).

    Attributes:
        radius [m] (n_grains,); driven_fraction x_ref / l_ref [-] (n_grains, dim); free_dofs (grain, axis)
        int64 (n_free, 2); pairs int64 (n_pairs, 2); outer: polygon int64 (n_outer,) or triangles
        (n_faces, 3); kn, kt [N/m], mu [-], contact_tolerance [-].
    """

    radius: np.ndarray
    driven_fraction: np.ndarray
    free_dofs: np.ndarray
    pairs: np.ndarray
    outer: np.ndarray
    kn: float
    kt: float
    mu: float
    contact_tolerance: float

    @property
    def dim(self) -> int:
        """Dimension of the cells (2 or 3)."""
        return int(self.driven_fraction.shape[1])

    @property
    def shear_shape(self) -> tuple[int, ...]:
        """Shape of one cell's tangential springs: (n_pairs,) planar, (n_pairs, 3) spatial."""
        return (int(self.pairs.shape[0]), *dimension(self.dim).spring_shape)

    @property
    def diameter(self) -> float:
        """Length scale D [m]: the mean grain diameter (as ``CellSchema.diameter``)."""
        return float(2.0 * self.radius.mean())


@dataclass(frozen=True)
class NetArrays:
    """A trained ``MesoNet`` as numpy arrays: ``schema``; ``active_index`` int64, the active pairs;
    ``feature_mean``, ``feature_std`` (n_features,), ``rate_mean``, ``rate_std`` (n_free,) float64;
    ``layers``: (weight (n_out, n_in), bias (n_out,)) per layer, input layer first."""

    schema: SchemaArrays
    active_index: np.ndarray
    feature_mean: np.ndarray
    feature_std: np.ndarray
    rate_mean: np.ndarray
    rate_std: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]


def schema_arrays(arrays: Mapping[str, Any], *, kn: float, kt_over_kn: float, phi_g_deg: float,
                  contact_tolerance: float) -> SchemaArrays:
    """``SchemaArrays`` of a checkpoint's ``schema`` dict and a contact law (the formulas of
    ``training.dataset.schema_from_arrays`` and ``CellSchema.from_arrays``)."""
    driven = np.asarray(arrays["driven"], dtype=bool)
    fraction = np.asarray(arrays["reference_position"], float) / np.asarray(arrays["reference_cell_size"], float)[None, :]
    return SchemaArrays(np.array(arrays["radius"], dtype=np.float64), np.array(fraction, dtype=np.float64),
                        np.argwhere(~driven).astype(np.int64), np.array(arrays["pairs"], dtype=np.int64),
                        np.array(arrays["outer"], dtype=np.int64), float(kn), float(kt_over_kn * kn),
                        float(math.tan(math.radians(phi_g_deg))), float(contact_tolerance))


def net_arrays(path: str | Path, metadata: Mapping[str, Any]) -> NetArrays:
    """The network saved at ``path`` (``training.checkpoint.save_checkpoint``) with its JSON ``metadata``.

    Raises ``StateDictError`` (one line) where the file does not hold the architecture the JSON
    describes."""
    state = read_state_dict(path)
    law = metadata["contact_law"]
    schema = schema_arrays(metadata["schema"], kn=float(law["kn"]), kt_over_kn=float(law["kt_over_kn"]),
                           phi_g_deg=float(law["phi_g_deg"]), contact_tolerance=float(metadata["contact_tolerance"]))
    n_layers = len(metadata["architecture"]["hidden"]) + 1
    try:
        layers = tuple((state[f"mlp.{2 * k}.weight"], state[f"mlp.{2 * k}.bias"]) for k in range(n_layers))
        active = np.asarray(state["active"], dtype=bool)
        stats = [np.ascontiguousarray(state[k], dtype=np.float64)
                 for k in ("feature_mean", "feature_std", "rate_mean", "rate_std")]
    except KeyError as exc:
        raise StateDictError(f"{path}: state_dict has no {exc.args[0]!r} (another architecture than its JSON's)") from None
    if (active.shape != (schema.pairs.shape[0],) or layers[0][0].shape[1] != stats[0].shape[0]
            or stats[2].shape != (schema.free_dofs.shape[0],)):
        raise StateDictError(f"{path}: state_dict does not match the architecture in its JSON")
    return NetArrays(schema, np.flatnonzero(active).astype(np.int64), *stats, layers)


def arrays_of_net(net: Any) -> NetArrays:
    """``NetArrays`` of a ``training.network.MesoNet`` (its tensors copied to numpy)."""
    as_np = lambda t, dtype=np.float64: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)  # noqa: E731
    s = net.schema
    schema = SchemaArrays(as_np(s.radius), as_np(s.driven_fraction), as_np(s.free_dofs, np.int64),
                          as_np(s.pairs, np.int64), as_np(s.outer, np.int64), float(s.kn), float(s.kt), float(s.mu),
                          float(s.contact_tolerance))
    linear = [m for m in net.mlp if hasattr(m, "weight")]
    return NetArrays(schema, as_np(net.active_index, np.int64), as_np(net.feature_mean), as_np(net.feature_std),
                     as_np(net.rate_mean), as_np(net.rate_std),
                     tuple((as_np(m.weight), as_np(m.bias)) for m in linear))


class Contacts(NamedTuple):
    """``training.cell_physics.Contacts`` on numpy arrays: branch (n, n_pairs, dim) [m], distance,
    overlap [m], contact (bool), normal_force [N] (n, n_pairs); normal, tangent (2D; None in 3D)
    unit vectors (n, n_pairs, dim)."""

    branch: np.ndarray
    distance: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray | None
    overlap: np.ndarray
    contact: np.ndarray
    normal_force: np.ndarray


def positions(schema: SchemaArrays, cell_size: np.ndarray, free_position: np.ndarray) -> np.ndarray:
    """Grain centres [m], (n, n_grains, dim): driven x = frac l, free as given (``cell_physics.positions``)."""
    x = schema.driven_fraction[None] * np.asarray(cell_size, dtype=np.float64)[:, None, :]
    x[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]] = free_position
    return x


def contacts(schema: SchemaArrays, x: np.ndarray) -> Contacts:
    """Geometry and normal forces of every pair at grain centres ``x`` (``cell_physics.contacts``)."""
    b = x[:, schema.pairs[:, 1]] - x[:, schema.pairs[:, 0]]
    dist2 = b[..., 0] * b[..., 0] + b[..., 1] * b[..., 1]
    for axis in range(2, b.shape[-1]):
        dist2 = dist2 + b[..., axis] * b[..., axis]
    dist = np.sqrt(dist2)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = b / dist[..., None]
    w = np.stack([-u[..., 1], u[..., 0]], axis=-1) if schema.dim == 2 else None
    rsum = schema.radius[schema.pairs[:, 0]] + schema.radius[schema.pairs[:, 1]]
    overlap = rsum - dist
    contact = dist <= rsum * (1.0 + schema.contact_tolerance)
    return Contacts(b, dist, u, w, overlap, contact, np.where(contact, schema.kn * np.maximum(overlap, 0.0), 0.0))


def pair_forces(c: Contacts, shear_force: np.ndarray) -> np.ndarray:
    """Force on grain i of each pair by grain j [N], (n, n_pairs, dim) (``cell_physics.pair_forces``)."""
    if c.tangent is None:
        return -c.normal_force[..., None] * c.normal + np.where(c.contact[..., None], shear_force, 0.0)
    return -c.normal_force[..., None] * c.normal + np.where(c.contact, shear_force, 0.0)[..., None] * c.tangent


def love_weber(c: Contacts, force_on_i: np.ndarray) -> np.ndarray:
    """Compression-positive Love-Weber moment -sum_c f_c (x) l_c [N m], (n, dim, dim)."""
    return -np.einsum("cpa,cpb->cab", force_on_i, c.branch)
