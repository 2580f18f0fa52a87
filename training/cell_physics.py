"""Exact generic cell physics in torch (float64): geometry, contact law, unbalanced forces, Love-Weber.

Everything here holds for ANY few-grain mesostructure; nothing solves an equilibrium. The
meso-ANN (``training.network``) decides where the free degrees of freedom go; this module
turns that decision into forces and stress exactly as the DEM's contact law does
(spec sections 4, 7, 10, 12).

Generic cell state (first axis n_cells), for planar (dim = 2) and spatial (dim = 3) cells:

- ``cell_size`` (n, dim) [m]: (l1, l2[, l3]);
- ``free_position`` (n, n_free) [m]: the free DOF coordinates, in the row-major order of
  ``driven == False`` (grain, axis);
- ``shear_force`` [N]: tangential spring force of each candidate pair, the DEM's convention
  (``warp_hcell.dem.kernels``, ``warp_hcell.dem.kernels3d``): in 2D (n, n_pairs), the force on
  grain i along w = (-u_t, u_n) with ``u = (x_j - x_i) / |x_j - x_i|``; in 3D (n, n_pairs, 3),
  the force vector on grain i in the contact's tangent plane.

Driven coordinates follow the cell strain exactly: x = (x_ref / l_ref) * l.

Conventions: local frame index 0 = n, 1 = t (3D: 1 = t1, 2 = t2). The contact force on grain
i of pair (i, j) is -f_n u + f_s w in 2D, -f_n u + f_s in 3D (f_n >= 0, repulsive); grain j
receives the opposite. Moments returned by ``love_weber`` are compression positive (the
DEM's tension-positive sum, negated). V_cell is the polygon area in 2D, the polyhedron volume
of the outer triangles in 3D (``cell_measure``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from warp_hcell.core.contact import CAP_SLACK
from warp_hcell.core.contract import SchemaCounts


@dataclass(frozen=True, eq=False)
class CellSchema(SchemaCounts):
    """Topology and reference geometry of a mesostructure, as tensors (float64/int64, CPU or device).

    Attributes:
        radius: grain radii [m], (n_grains,).
        driven_fraction: x_ref / l_ref of every coordinate [-], (n_grains, dim); used for the
            driven coordinates only.
        driven: bool (n_grains, dim).
        free_dofs: (grain, axis) of every free DOF, int64 (n_free, 2).
        pairs: candidate contact pairs (i, j), int64 (n_pairs, 2).
        outer: ordered grain indices of the polygon whose area is V_cell, int64 (n_outer,); in
            3D the outer triangles of the polyhedron whose volume is V_cell, int64 (n_faces, 3).
        kn, kt [N/m], mu [-]: contact law; contact_tolerance [-]: a gap up to
            contact_tolerance * (r_i + r_j) still counts as a contact (carrying zero force).
    """

    radius: torch.Tensor
    driven_fraction: torch.Tensor
    driven: torch.Tensor
    free_dofs: torch.Tensor
    pairs: torch.Tensor
    outer: torch.Tensor
    kn: float
    kt: float
    mu: float
    contact_tolerance: float

    @classmethod
    def from_arrays(cls, *, radius, reference_position, reference_cell_size, driven, pairs, outer,
                    kn: float, kt: float, mu: float, contact_tolerance: float) -> "CellSchema":
        """Schema from numpy arrays (the database's ``schema`` group or a ``Mesostructure``)."""
        driven = np.asarray(driven, dtype=bool)
        free = np.argwhere(~driven).astype(np.int64)
        fraction = np.asarray(reference_position, float) / np.asarray(reference_cell_size, float)[None, :]
        as64 = lambda a: torch.as_tensor(np.array(a, dtype=np.float64))  # noqa: E731
        return cls(radius=as64(radius), driven_fraction=as64(fraction), driven=torch.as_tensor(driven.copy()),
                   free_dofs=torch.as_tensor(free), pairs=torch.as_tensor(np.array(pairs, dtype=np.int64)),
                   outer=torch.as_tensor(np.array(outer, dtype=np.int64)), kn=float(kn), kt=float(kt),
                   mu=float(mu), contact_tolerance=float(contact_tolerance))

    @property
    def diameter(self) -> float:
        """Length scale D [m]: the mean grain diameter."""
        return float(2.0 * self.radius.mean())

    def to(self, device: torch.device | str) -> "CellSchema":
        """The same schema with its tensors on ``device``."""
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return CellSchema(**moved)


def positions(schema: CellSchema, cell_size: torch.Tensor, free_position: torch.Tensor) -> torch.Tensor:
    """Grain centres [m], (n, n_grains, dim): driven coordinates from ``cell_size``, free ones given."""
    x = schema.driven_fraction.unsqueeze(0) * cell_size.unsqueeze(1)
    flat = x.reshape(x.shape[0], -1)
    index = (schema.free_dofs[:, 0] * schema.dim + schema.free_dofs[:, 1]).unsqueeze(0).expand(x.shape[0], -1)
    return flat.scatter(1, index, free_position).reshape(x.shape)


def branches(schema: CellSchema, x: torch.Tensor) -> torch.Tensor:
    """Branch vectors x_j - x_i [m] of every candidate pair, (n, n_pairs, dim)."""
    return x[:, schema.pairs[:, 1]] - x[:, schema.pairs[:, 0]]


@dataclass(frozen=True)
class Contacts:
    """Contact quantities of every candidate pair, (n, n_pairs) each unless stated.

    Attributes:
        branch: x_j - x_i [m], (n, n_pairs, dim); distance [m]; normal u and, in 2D, tangent w
            unit vectors (n, n_pairs, dim) (3D: ``tangent`` is None, the spring is a vector);
            overlap r_i + r_j - distance [m] (negative = gap);
        contact: bool, gap within the contact tolerance; normal_force f_n >= 0 [N].
    """

    branch: torch.Tensor
    distance: torch.Tensor
    normal: torch.Tensor
    tangent: torch.Tensor | None
    overlap: torch.Tensor
    contact: torch.Tensor
    normal_force: torch.Tensor


def normal_force(overlap: torch.Tensor, kn: float) -> torch.Tensor:
    """Normal (repulsive) force kn max(overlap, 0) [N], never tension (``warp_hcell.core.contact``)."""
    return kn * torch.clamp(overlap, min=0.0)


def coulomb_cap(trial: torch.Tensor, normal: torch.Tensor, mu: float) -> torch.Tensor:
    """The trial tangential force [N] capped at mu f_n with its own sign: clip(trial, -mu f_n, mu f_n)."""
    cap = mu * normal
    return torch.minimum(torch.maximum(trial, -cap), cap)


def contacts(schema: CellSchema, x: torch.Tensor) -> Contacts:
    """Geometry and normal forces (linear spring, no tension) of the pairs of grains at ``x``."""
    b = branches(schema, x)
    dist = torch.linalg.vector_norm(b, dim=-1)
    u = b / dist.unsqueeze(-1)
    w = SPRINGS[schema.dim].tangent(u)
    rsum = schema.radius[schema.pairs[:, 0]] + schema.radius[schema.pairs[:, 1]]
    overlap = rsum - dist
    contact = dist <= rsum * (1.0 + schema.contact_tolerance)
    return Contacts(b, dist, u, w, overlap, contact,
                    torch.where(contact, normal_force(overlap, schema.kn), torch.zeros_like(overlap)))


def pair_forces(c: Contacts, shear_force: torch.Tensor) -> torch.Tensor:
    """Force on grain i of each pair by grain j [N], (n, n_pairs, dim): -f_n u + f_s w in 2D,
    -f_n u + f_s in 3D (0 out of contact)."""
    if c.tangent is None:
        fs = torch.where(c.contact.unsqueeze(-1), shear_force, torch.zeros_like(shear_force))
        return -c.normal_force.unsqueeze(-1) * c.normal + fs
    fs = torch.where(c.contact, shear_force, torch.zeros_like(shear_force))
    return -c.normal_force.unsqueeze(-1) * c.normal + fs.unsqueeze(-1) * c.tangent


def unbalanced(schema: CellSchema, force_on_i: torch.Tensor, n_grains: int) -> torch.Tensor:
    """Net contact force on every free DOF [N], (n, n_free)."""
    n = force_on_i.shape[0]
    net = torch.zeros(n, n_grains, force_on_i.shape[-1], dtype=force_on_i.dtype, device=force_on_i.device)
    net = net.index_add(1, schema.pairs[:, 0], force_on_i).index_add(1, schema.pairs[:, 1], -force_on_i)
    return net[:, schema.free_dofs[:, 0], schema.free_dofs[:, 1]]


def love_weber(c: Contacts, force_on_i: torch.Tensor) -> torch.Tensor:
    """Compression-positive Love-Weber moment -sum_c f_c (x) l_c [N m], (n, dim, dim)."""
    return -torch.einsum("cpa,cpb->cab", force_on_i, c.branch)


def polygon_area(x: torch.Tensor, outer: torch.Tensor) -> torch.Tensor:
    """Area [m^2], (n,), of the polygon through the centres ``x[:, outer]`` (shoelace)."""
    p = x[:, outer]
    q = torch.roll(p, -1, dims=1)
    return 0.5 * torch.abs(torch.sum(p[..., 0] * q[..., 1] - q[..., 0] * p[..., 1], dim=1))


def polyhedron_volume(x: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Volume [m^3], (n,), enclosed by the triangles ``faces`` (n_faces, 3) through ``x`` (n, n_grains, 3):
    abs(sum_f x_a . (x_b x x_c)) / 6."""
    a, b, c = x[:, faces[:, 0]], x[:, faces[:, 1]], x[:, faces[:, 2]]
    return torch.abs(torch.sum(a * torch.linalg.cross(b, c), dim=(1, 2))) / 6.0


def cell_measure(x: torch.Tensor, outer: torch.Tensor) -> torch.Tensor:
    """V_cell [m^2 or m^3], (n,): ``polygon_area`` for a polygon ``outer`` (n_outer,), ``polyhedron_volume``
    for triangles (n_faces, 3)."""
    return polygon_area(x, outer) if outer.dim() == 1 else polyhedron_volume(x, outer)


def carried_spring(shear_force: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """Spatial springs (..., 3) carried into the tangent plane of the unit ``normal`` (..., 3):
    projected, then rescaled to their former magnitude (zero stays zero), as the 3D DEM does
    (``warp_hcell.dem.contact.carried_spring``)."""
    projected = shear_force - torch.sum(shear_force * normal, dim=-1, keepdim=True) * normal
    before2 = torch.sum(shear_force * shear_force, dim=-1, keepdim=True)
    after2 = torch.sum(projected * projected, dim=-1, keepdim=True)
    positive = after2 > 0
    return torch.where(positive, projected * torch.sqrt(before2 / torch.where(positive, after2, 1.0)), projected)


def coulomb_cap_vector(trial: torch.Tensor, normal: torch.Tensor, mu: float) -> torch.Tensor:
    """Spatial trial springs (..., 3) scaled down to mu f_n (f_n: ``normal`` (...)) along their own
    direction where longer by more than ``warp_hcell.core.contact.CAP_SLACK`` (the 3D DEM's cap)."""
    size = torch.linalg.vector_norm(trial, dim=-1)
    cap = mu * normal
    scale = torch.where(size > cap * (1.0 + CAP_SLACK), cap / torch.where(size > 0, size, 1.0), 1.0)
    return trial * scale.unsqueeze(-1)


def _rotated(u: torch.Tensor) -> torch.Tensor:
    """Planar unit tangents w = (-u_t, u_n) (..., 2) of unit normals ``u`` (..., 2)."""
    return torch.stack([-u[..., 1], u[..., 0]], dim=-1)


def _scalar_spring(schema: CellSchema, old: Contacts, new: Contacts, shear_force: torch.Tensor, mid: torch.Tensor,
                   relative: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Planar springs (n, n_pairs) after an increment, and where the Coulomb cap acted (``advance``)."""
    w_mid = _rotated(mid)
    trial = torch.where(old.contact, shear_force, torch.zeros_like(shear_force)) + schema.kt * torch.sum(relative * w_mid, dim=-1)
    shear = torch.where(new.contact, coulomb_cap(trial, new.normal_force, schema.mu), torch.zeros_like(trial))
    return shear, new.contact & (torch.abs(trial) > schema.mu * new.normal_force)


def _vector_spring(schema: CellSchema, old: Contacts, new: Contacts, shear_force: torch.Tensor, mid: torch.Tensor,
                   relative: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Spatial springs (n, n_pairs, 3) after an increment, and where the Coulomb cap acted (``advance``)."""
    carried = torch.where(old.contact.unsqueeze(-1), carried_spring(shear_force, new.normal),
                          torch.zeros_like(shear_force))
    slip = relative - torch.sum(relative * mid, dim=-1, keepdim=True) * mid
    trial = carried + schema.kt * slip
    shear = torch.where(new.contact.unsqueeze(-1), coulomb_cap_vector(trial, new.normal_force, schema.mu),
                        torch.zeros_like(trial))
    return shear, new.contact & (torch.linalg.vector_norm(trial, dim=-1) > schema.mu * new.normal_force)


@dataclass(frozen=True)
class Spring:
    """The tangential spring of one dimension: a scalar along w in the plane, a vector in the
    contact's tangent plane in space (module docstring).

    Attributes:
        tangent: unit normals u (..., dim) -> the unit tangents w (..., dim) of a scalar spring,
            or None (a vector spring needs none).
        update: (schema, contacts before, contacts after, springs before [N], unit mid-increment
            normals (n, n_pairs, dim), branch change (n, n_pairs, dim) [m]) -> (the new springs [N],
            bool (n, n_pairs): the Coulomb cap acted); ``advance`` documents the law.
    """

    tangent: Callable[[torch.Tensor], torch.Tensor | None]
    update: Callable[..., tuple[torch.Tensor, torch.Tensor]]


SPRINGS = {2: Spring(_rotated, _scalar_spring), 3: Spring(lambda u: None, _vector_spring)}
"""The tangential spring of a cell by its dimension."""


@dataclass(frozen=True)
class Increment:
    """Outcome of ``advance`` (first axis n_cells).

    Attributes:
        cell_size: the new cell size [m], (n, dim).
        free_position: the new free DOF coordinates [m], (n, n_free).
        shear_force: the new tangential spring forces [N], (n, n_pairs) (3D: (n, n_pairs, 3)).
        moment: compression-positive Love-Weber moment [N m], (n, dim, dim).
        area: V_cell [m^2] (3D: [m^3]), (n,).
        capped: bool (n, n_pairs), the trial tangential force exceeded the Coulomb cap mu f_n;
        opened: bool (n, n_pairs), a pair that carried a normal force lost it (no-tension branch);
        held: bool (n, n_free), free DOFs of grains held at rest (``hold_at_rest``); None where
            the rule was not applied.
    """

    cell_size: torch.Tensor
    free_position: torch.Tensor
    shear_force: torch.Tensor
    moment: torch.Tensor
    area: torch.Tensor
    capped: torch.Tensor
    opened: torch.Tensor
    held: torch.Tensor | None = None


def grains_touched(schema: CellSchema, contact: torch.Tensor) -> torch.Tensor:
    """Grains with at least one pair in ``contact`` (bool (n, n_pairs)), bool (n, n_grains)."""
    flags = contact.to(torch.float64)
    touched = torch.zeros(contact.shape[0], int(schema.radius.shape[0]), dtype=torch.float64, device=flags.device)
    return touched.index_add(1, schema.pairs[:, 0], flags).index_add(1, schema.pairs[:, 1], flags) > 0


def hold_at_rest(schema: CellSchema, new_size: torch.Tensor, free_position: torch.Tensor, d_free: torch.Tensor,
                 old: Contacts) -> tuple[torch.Tensor, torch.Tensor]:
    """The DEM's rest rule for one increment: a free grain with zero force that nothing reaches does not move.

    A free grain with no pair within the contact tolerance at the start stays where it is unless
    reached: one of its pairs is within the tolerance at the end of the increment, with every held
    grain at rest and the other free DOFs moved by ``d_free``; a reached grain keeps ``d_free``.
    Repeated until no grain is released (at most n_grains passes), so a chain of touching grains is
    pushed within the increment, as in the DEM.

    Args:
        new_size: cell size at the end of the increment [m], (n, dim).
        free_position: free DOFs at the start [m], (n, n_free); d_free: their displacement [m], (n, n_free).
        old: ``contacts`` of the state at the start.

    Returns:
        (d_free with the rows of held DOFs set to zero, held: bool (n, n_free))."""
    grain = schema.free_dofs[:, 0]
    held = ~grains_touched(schema, old.contact)[:, grain]
    with torch.no_grad():
        for _ in range(int(schema.radius.shape[0])):
            trial = free_position + torch.where(held, torch.zeros_like(d_free), d_free)
            reached = grains_touched(schema, contacts(schema, positions(schema, new_size, trial)).contact)[:, grain]
            still = held & ~reached
            if torch.equal(still, held):
                break
            held = still
    return torch.where(held, torch.zeros_like(d_free), d_free), held


def count_held_grains(schema: CellSchema, held: torch.Tensor) -> torch.Tensor:
    """Grains held at rest per cell, int64 (n,), from the per-DOF flags ``held`` (n, n_free)."""
    per_grain = torch.zeros(held.shape[0], int(schema.radius.shape[0]), dtype=torch.bool, device=held.device)
    per_grain[:, schema.free_dofs[:, 0]] = held
    return per_grain.sum(dim=1)


def advance(schema: CellSchema, cell_size: torch.Tensor, free_position: torch.Tensor, shear_force: torch.Tensor,
            d_eps: torch.Tensor, d_free: torch.Tensor, old: Contacts | None = None, *,
            rest_rule: bool = False) -> Increment:
    """Apply a strain increment and a free-DOF displacement with the contact law (spec sections 3, 4, 12).

    Args:
        cell_size, free_position, shear_force: state before the increment (module docstring).
        d_eps: local strain increment [-], (n, dim), compression positive: l <- l (1 - d_eps).
        d_free: displacement of the free DOFs over the increment [m], (n, n_free).
        old: ``contacts`` of the state before the increment, when already computed.
        rest_rule: apply ``hold_at_rest`` to ``d_free`` first and report the held DOFs in
            ``Increment.held``.

    Returns:
        The new state with its moment and area. The spring (3D: first carried into the new tangent
        plane, ``carried_spring``) grows by kt times the relative tangential displacement about the
        mid-increment normal, is capped at mu f_n along its trial direction
        (``coulomb_cap_vector``) and is reset out of contact."""
    if old is None:
        old = contacts(schema, positions(schema, cell_size, free_position))
    new_size = cell_size * (1.0 - d_eps)
    held = None
    if rest_rule:
        d_free, held = hold_at_rest(schema, new_size, free_position, d_free, old)
    new_free = free_position + d_free
    x_new = positions(schema, new_size, new_free)
    new = contacts(schema, x_new)
    mid = 0.5 * (old.branch + new.branch)
    mid = mid / torch.linalg.vector_norm(mid, dim=-1, keepdim=True)
    relative = new.branch - old.branch
    shear, capped = SPRINGS[schema.dim].update(schema, old, new, shear_force, mid, relative)
    opened = (old.normal_force > 0.0) & (new.normal_force == 0.0)
    force = pair_forces(new, shear)
    return Increment(new_size, new_free, shear, love_weber(new, force), cell_measure(x_new, schema.outer), capped,
                     opened, held)
