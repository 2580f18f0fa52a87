"""``MesoNet``: the generic meso-ANN (spec section 12): where do the free DOFs of a cell go?

Contract. For a batch of generic cell states (``training.cell_physics``: cell size, free-DOF
coordinates, per-pair tangential forces) and probes d_eps [-] of ``dim`` components
(compression positive), ``MesoNet.displacement`` returns the displacement of every free DOF
over the increment [m], shape (n, n_free):

    d_free = D * m * r(state, u)  -  C(state) @ F / kn

with ``m = |d_eps|``, u = d_eps / m (u = 0 where m = 0), D the mean grain diameter, F the
unbalanced contact force on the free DOFs [N] (exact, from the contact law) and kn the normal
stiffness. r (free-DOF rates per unit probe magnitude, in D) and C (an n_free x n_free
compliance in units of 1/kn) are outputs of one tanh multilayer perceptron. The first term is
homogeneous of degree one in the probe; the second returns a recurrent model towards
equilibrium (trained on perturbed states that the DEM relaxes).

Features (z-scored with training statistics), for any mesostructure:

    - the probe direction u;
    - cell size l / D; free coordinates x / D and x / l (l of the coordinate's axis);
    - per active pair (in contact somewhere in the training data): overlap / D (gaps clipped
      at ``GAP_CLIP``), the contact flag, the branch direction, the tangential force / (kn D)
      and the friction ratio ``|f_s| / (mu f_n)`` (0 out of contact; ``pair_features``);
    - optionally (``load_features``), per active pair the load fraction f_n / max f_n over the
      cell's pairs (0 in a cell carrying none), which tells a barely loaded contact at low
      pressure from one just touching.

Nothing here knows any particular cell; the dimension is the schema's. Everything is float64
(positions must be resolved to ~1e-7 D).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from torch import nn

from training import cell_physics
from training.cell_physics import CellSchema
from training.config import DEFAULT_HIDDEN
from training.fast_model import ACTIVATION, COMPLIANCE_SCALE, GAP_CLIP, RELAXATION_RAMP  # noqa: F401 (torch-free home)

PAIR_FEATURES = ("overlap", "contact", "branch_n", "branch_t", "shear", "friction_ratio")
"""Features of each active pair of a planar cell."""
PAIR_FEATURES_3D = ("overlap", "contact", "branch_n", "branch_t1", "branch_t2", "shear_n", "shear_t1", "shear_t2",
                    "friction_ratio")
"""Features of each active pair of a spatial cell."""


def _planar_pairs(overlap, contact, closed, fn, normal, shear_force, mu: float, force_scale: float) -> torch.Tensor:
    """``PAIR_FEATURES`` columns (n, n_active, 6) of a planar cell's active pairs (``features_and_contacts``)."""
    fs = torch.where(contact, shear_force, 0.0)
    ratio = torch.where(closed, fs / (mu * torch.where(closed, fn, 1.0)), 0.0)
    return torch.stack([overlap, contact.to(fn.dtype), normal[..., 0], normal[..., 1], fs / force_scale, ratio], dim=2)


def _spatial_pairs(overlap, contact, closed, fn, normal, shear_force, mu: float, force_scale: float) -> torch.Tensor:
    """``PAIR_FEATURES_3D`` columns (n, n_active, 9) of a spatial cell's active pairs (``features_and_contacts``)."""
    fs = torch.where(contact.unsqueeze(-1), shear_force, 0.0)
    size = torch.linalg.vector_norm(fs, dim=-1)
    ratio = torch.where(closed, size / (mu * torch.where(closed, fn, 1.0)), 0.0)
    return torch.cat([overlap.unsqueeze(-1), contact.to(fn.dtype).unsqueeze(-1), normal, fs / force_scale,
                      ratio.unsqueeze(-1)], dim=2)


@dataclass(frozen=True)
class PairFeatures:
    """The features of each active pair of a cell of one dimension.

    Attributes:
        names: the features' names, in input order.
        columns: (overlap / D clipped, contact bool, closed bool, f_n [N], unit normals (..., dim),
            springs [N] (n, n_active[, 3]), mu, kn D [N]) of the active pairs -> their features
            (n, n_active, len(names)).
    """

    names: tuple[str, ...]
    columns: Callable[..., torch.Tensor]


PAIRS = {2: PairFeatures(PAIR_FEATURES, _planar_pairs), 3: PairFeatures(PAIR_FEATURES_3D, _spatial_pairs)}
"""The pair features of a cell by its dimension."""


def pair_features(dim: int) -> tuple[str, ...]:
    """Names of the features of each active pair of a cell of dimension ``dim``, in input order."""
    return PAIRS[dim].names


def features(schema: CellSchema, active: torch.Tensor, cell_size: torch.Tensor, free_position: torch.Tensor,
             shear_force: torch.Tensor, d_eps: torch.Tensor, load_features: bool = False,
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw features, probe magnitudes and unbalanced forces of a batch of cells (``features_and_contacts``)."""
    return features_and_contacts(schema, active, cell_size, free_position, shear_force, d_eps, load_features)[:3]


def features_and_contacts(schema: CellSchema, active: torch.Tensor, cell_size: torch.Tensor, free_position: torch.Tensor,
                          shear_force: torch.Tensor, d_eps: torch.Tensor, load_features: bool = False):
    """Raw features, probe magnitudes, unbalanced forces and contacts of a batch of cells.

    Args:
        schema: the mesostructure; active: pairs the network sees, bool (n_pairs,) or their
            indices (int64, ascending).
        cell_size: cell size before the increment [m], (n, dim).
        free_position: free DOF coordinates before the increment [m], (n, n_free).
        shear_force: tangential spring forces before the increment [N], (n, n_pairs)
            (3D: (n, n_pairs, 3)).
        d_eps: the probe [-], (n, dim).
        load_features: append the load fraction of every active pair (module docstring).

    Returns:
        (features (n, n_features), ``m = |d_eps|`` (n, 1), F (n, n_free) [N], the
        ``cell_physics.Contacts`` of the state).
    """
    diameter = schema.diameter
    force_scale = schema.kn * diameter
    m = torch.linalg.vector_norm(d_eps, dim=1, keepdim=True)
    u = torch.where(m > 0, d_eps / torch.where(m > 0, m, torch.ones_like(m)), torch.zeros_like(d_eps))
    x = cell_physics.positions(schema, cell_size, free_position)
    c = cell_physics.contacts(schema, x)
    force = cell_physics.pair_forces(c, shear_force)
    unbalanced = cell_physics.unbalanced(schema, force, int(schema.radius.shape[0]))
    axis_length = cell_size[:, schema.free_dofs[:, 1]]
    index = torch.nonzero(active)[:, 0] if active.dtype == torch.bool else active
    contact = c.contact.index_select(1, index)
    fn = c.normal_force.index_select(1, index)
    closed = fn > 0
    normal = c.normal.index_select(1, index)
    overlap = torch.clamp(c.overlap.index_select(1, index) / diameter, min=-GAP_CLIP)
    pair = PAIRS[schema.dim].columns(overlap, contact, closed, fn, normal, shear_force.index_select(1, index),
                                     schema.mu, force_scale)
    feats = torch.cat([u, cell_size / diameter, free_position / diameter, free_position / axis_length,
                       pair.reshape(pair.shape[0], -1)], dim=1)
    if load_features:
        largest = c.normal_force.amax(dim=1, keepdim=True)
        loaded = largest > 0
        feats = torch.cat([feats, torch.where(loaded, fn / torch.where(loaded, largest, 1.0), 0.0)], dim=1)
    return feats, m, unbalanced, c


def n_features(n_free: int, n_active: int, load_features: bool = False, dim: int = 2) -> int:
    """Number of features for ``n_free`` free DOFs and ``n_active`` active pairs (and their load
    fractions) of a cell of dimension ``dim``."""
    return 2 * dim + 2 * n_free + (len(pair_features(dim)) + int(load_features)) * n_active


class MesoNet(nn.Module):
    """Tanh multilayer perceptron with its schema and normalisation (float64).

    Args:
        schema: the mesostructure the network is trained for.
        active: bool (n_pairs,), candidate pairs whose features the network sees.
        hidden: widths of the hidden layers.
        load_features: whether the inputs end with the load fraction of every active pair.

    Buffers (restored by ``load_state_dict``): ``active``, ``feature_mean``, ``feature_std``
    (n_features,), ``rate_mean``, ``rate_std`` (n_free,) [D per unit strain].
    """

    def __init__(self, schema: CellSchema, active: torch.Tensor, hidden: Sequence[int] = DEFAULT_HIDDEN,
                 load_features: bool = False) -> None:
        super().__init__()
        self.schema = schema
        self.hidden = tuple(int(h) for h in hidden)
        if not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"hidden = {list(self.hidden)} must be a non-empty list of widths >= 1")
        self.n_free = schema.n_free
        self.load_features = bool(load_features)
        active = torch.as_tensor(active, dtype=torch.bool)
        n_in = n_features(self.n_free, int(active.sum()), self.load_features, schema.dim)
        widths = (n_in, *self.hidden)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(a, b, dtype=torch.float64), nn.Tanh()]
        last = nn.Linear(widths[-1], self.n_free + self.n_free**2, dtype=torch.float64)
        with torch.no_grad():
            last.weight.mul_(0.1)
            last.bias.zero_()
        layers.append(last)
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("active", active.clone())
        self.active_index = torch.nonzero(active)[:, 0]
        self.register_buffer("feature_mean", torch.zeros(n_in, dtype=torch.float64))
        self.register_buffer("feature_std", torch.ones(n_in, dtype=torch.float64))
        self.register_buffer("rate_mean", torch.zeros(self.n_free, dtype=torch.float64))
        self.register_buffer("rate_std", torch.ones(self.n_free, dtype=torch.float64))

    def set_normalisation(self, feature_mean, feature_std, rate_mean, rate_std) -> None:
        """Copy z-score statistics into the buffers."""
        for name, value in (("feature_mean", feature_mean), ("feature_std", feature_std),
                            ("rate_mean", rate_mean), ("rate_std", rate_std)):
            getattr(self, name).copy_(torch.as_tensor(value, dtype=torch.float64))

    def raw_features(self, cell_size, free_position, shear_force, d_eps):
        """``features`` with this network's schema and active pairs."""
        return features(self.schema, self.active_index, cell_size, free_position, shear_force, d_eps,
                        self.load_features)

    def displacement_from_features(self, feats: torch.Tensor, m: torch.Tensor, unbalanced: torch.Tensor,
                                   relaxation: torch.Tensor | float = 1.0) -> torch.Tensor:
        """Free-DOF displacement [m], (n, n_free), from raw features, ``|d_eps|`` and F (module docstring).

        ``relaxation`` (scalar or (n, 1)) multiplies the relaxation term -C F / kn.
        """
        out = self.mlp((feats - self.feature_mean) / self.feature_std)
        rate = out[:, :self.n_free] * self.rate_std + self.rate_mean
        eye = torch.eye(self.n_free, dtype=out.dtype, device=out.device)
        compliance = COMPLIANCE_SCALE * (eye + out[:, self.n_free:].reshape(-1, self.n_free, self.n_free))
        relax = torch.einsum("nij,nj->ni", compliance, unbalanced) / self.schema.kn
        return self.schema.diameter * m * rate - relaxation * relax

    def displacement(self, cell_size, free_position, shear_force, d_eps) -> torch.Tensor:
        """Free-DOF displacement [m], (n, n_free), over the probe ``d_eps`` (n, dim) from the given state."""
        return self.displacement_from_features(*self.raw_features(cell_size, free_position, shear_force, d_eps))

    def advance(self, cell_size, free_position, shear_force, d_eps) -> cell_physics.Increment:
        """One cell-increment: the network moves the free DOFs, the contact law gives the forces.

        Below ``|d_eps|`` = ``RELAXATION_RAMP`` the relaxation is scaled down linearly to zero. The
        DEM's rest rule holds free grains that carry no force and that nothing reaches
        (``cell_physics.hold_at_rest``; ``Increment.held`` flags them).
        """
        feats, m, unbalanced, old = features_and_contacts(self.schema, self.active_index, cell_size, free_position,
                                                          shear_force, d_eps, self.load_features)
        d_free = self.displacement_from_features(feats, m, unbalanced, torch.clamp(m / RELAXATION_RAMP, max=1.0))
        return cell_physics.advance(self.schema, cell_size, free_position, shear_force, d_eps, d_free, old,
                                    rest_rule=True)
