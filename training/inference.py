"""Fast no-autograd inference of ``MesoNet.advance``: compiled cell physics around one MLP call.

``FastAdvance`` gives the same increment as ``MesoNet.advance`` (``training.network``,
``training.cell_physics``) up to float rounding, for inference only (no autograd):

1. ``_features`` (numba, float64, one fused loop over cells): positions, contacts, pair
   forces, unbalanced forces and the z-scored features of the state before the increment;
2. the multilayer perceptron (torch, ``mlp_dtype``: float64 by default, float32 on request);
3. ``_advance`` (numba, float64): the free-DOF displacement from the network output, the
   new state by the contact law, its Love-Weber moment, area and contact-law branch flags.

The features are z-scored in float64 before the cast to ``mlp_dtype``, and the network
output is un-normalised in float64, so float32 only rounds the perceptron's own arithmetic
(its effect on whole runs is measured in ``docs/ann.md``). The physics stays float64
(positions must be resolved to ~1e-7 D). The tangent (autograd) uses ``MesoNet.advance``.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch

from training.network import COMPLIANCE_SCALE, GAP_CLIP, RELAXATION_RAMP, MesoNet


@numba.njit(cache=True, inline="always")
def _positions(size, free, c, frac, free_dofs, x):
    """Grain centres of cell ``c`` into ``x`` (n_grains, 2) [m]: driven ones from ``size``, free ones given."""
    for g in range(frac.shape[0]):
        x[g, 0] = frac[g, 0] * size[c, 0]
        x[g, 1] = frac[g, 1] * size[c, 1]
    for k in range(free_dofs.shape[0]):
        x[free_dofs[k, 0], free_dofs[k, 1]] = free[c, k]


@numba.njit(cache=True, inline="always")
def _contacts(x, pairs, radius, kn, tol, c, branch, u, overlap, contact, fn):
    """Branch x_j - x_i, unit normal, overlap, contact flag and normal force of every pair of cell ``c``."""
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        j = pairs[p, 1]
        b0 = x[j, 0] - x[i, 0]
        b1 = x[j, 1] - x[i, 1]
        branch[c, p, 0] = b0
        branch[c, p, 1] = b1
        d = math.sqrt(b0 * b0 + b1 * b1)
        u[p, 0] = b0 / d
        u[p, 1] = b1 / d
        rsum = radius[i] + radius[j]
        overlap[p] = rsum - d
        touching = d <= rsum * (1.0 + tol)
        contact[c, p] = touching
        fn[c, p] = kn * max(rsum - d, 0.0) if touching else 0.0


@numba.njit(cache=True)
def _features(size, free, shear, d_eps, frac, free_dofs, pairs, radius, active, feature_mean, feature_std,
              diameter, kn, mu, tol, gap_clip, feats, m_out, unbalanced, old_branch, old_contact, old_fn):
    """Z-scored features, |d_eps|, unbalanced forces and the contacts of every cell before its increment.

    Outputs (first axis n_cells): feats (n, n_features) (any float dtype), m_out (n,),
    unbalanced (n, n_free) [N], old_branch (n, n_pairs, 2) [m], old_contact (n, n_pairs)
    bool, old_fn (n, n_pairs) [N]. Feature order: ``training.network.features_and_contacts``.
    """
    n_cells = size.shape[0]
    n_grains = frac.shape[0]
    n_free = free_dofs.shape[0]
    n_pairs = pairs.shape[0]
    force_scale = kn * diameter
    inv_std = 1.0 / feature_std
    x = np.empty((n_grains, 2))
    net = np.empty((n_grains, 2))
    u = np.empty((n_pairs, 2))
    overlap = np.empty(n_pairs)
    f = np.empty((n_pairs, 2))
    row = np.empty(feature_mean.shape[0])
    for c in range(n_cells):
        _positions(size, free, c, frac, free_dofs, x)
        _contacts(x, pairs, radius, kn, tol, c, old_branch, u, overlap, old_contact, old_fn)
        for p in range(n_pairs):
            fs = shear[c, p] if old_contact[c, p] else 0.0
            fn = old_fn[c, p]
            f[p, 0] = -fn * u[p, 0] + fs * -u[p, 1]
            f[p, 1] = -fn * u[p, 1] + fs * u[p, 0]
        net[:, :] = 0.0
        for p in range(n_pairs):
            net[pairs[p, 0], 0] += f[p, 0]
            net[pairs[p, 0], 1] += f[p, 1]
        for p in range(n_pairs):
            net[pairs[p, 1], 0] -= f[p, 0]
            net[pairs[p, 1], 1] -= f[p, 1]
        for k in range(n_free):
            unbalanced[c, k] = net[free_dofs[k, 0], free_dofs[k, 1]]
        m = math.sqrt(d_eps[c, 0] * d_eps[c, 0] + d_eps[c, 1] * d_eps[c, 1])
        m_out[c] = m
        row[0] = d_eps[c, 0] / m if m > 0 else 0.0
        row[1] = d_eps[c, 1] / m if m > 0 else 0.0
        row[2] = size[c, 0] / diameter
        row[3] = size[c, 1] / diameter
        for k in range(n_free):
            row[4 + k] = free[c, k] / diameter
            row[4 + n_free + k] = free[c, k] / size[c, free_dofs[k, 1]]
        base = 4 + 2 * n_free
        for a in range(active.shape[0]):
            p = active[a]
            touching = old_contact[c, p]
            fs = shear[c, p] if touching else 0.0
            fn = old_fn[c, p]
            row[base] = max(overlap[p] / diameter, -gap_clip)
            row[base + 1] = 1.0 if touching else 0.0
            row[base + 2] = u[p, 0]
            row[base + 3] = u[p, 1]
            row[base + 4] = fs / force_scale
            row[base + 5] = fs / (mu * fn) if fn > 0 else 0.0
            base += 6
        for k in range(row.shape[0]):
            feats[c, k] = (row[k] - feature_mean[k]) * inv_std[k]


@numba.njit(cache=True)
def _advance(size, free, shear, d_eps, out, m_in, unbalanced, old_branch, old_contact, old_fn, frac, free_dofs,
             pairs, radius, outer, rate_mean, rate_std, compliance_scale, diameter, kn, kt, mu, tol, ramp,
             new_size, new_free, new_shear, moment, area, capped_any, opened_any):
    """Free-DOF displacement from the network output ``out`` (n, n_free + n_free^2), then the contact law.

    Outputs: the new state (new_size, new_free, new_shear), the compression-positive moment
    (n, 2, 2) [N m], the area (n,) [m^2] and per-cell flags (bool (n,)): a trial tangential
    force exceeded mu f_n; a pair carrying a normal force opened.
    """
    n_cells = size.shape[0]
    n_grains = frac.shape[0]
    n_free = free_dofs.shape[0]
    n_pairs = pairs.shape[0]
    x = np.empty((n_grains, 2))
    branch = np.empty((1, n_pairs, 2))
    u = np.empty((n_pairs, 2))
    overlap = np.empty(n_pairs)
    contact = np.empty((1, n_pairs), dtype=np.bool_)
    fn = np.empty((1, n_pairs))
    n_outer = outer.shape[0]
    for c in range(n_cells):
        m = m_in[c]
        relaxation = min(m / ramp, 1.0)
        for k in range(n_free):
            cf = 0.0
            for j in range(n_free):
                cij = compliance_scale * ((1.0 if j == k else 0.0) + float(out[c, n_free + k * n_free + j]))
                cf += cij * unbalanced[c, j]
            rate = float(out[c, k]) * rate_std[k] + rate_mean[k]
            new_free[c, k] = free[c, k] + (diameter * m * rate - relaxation * (cf / kn))
        new_size[c, 0] = size[c, 0] * (1.0 - d_eps[c, 0])
        new_size[c, 1] = size[c, 1] * (1.0 - d_eps[c, 1])
        _positions(new_size, new_free, c, frac, free_dofs, x)
        _contacts(x, pairs, radius, kn, tol, 0, branch, u, overlap, contact, fn)
        s00 = 0.0
        s01 = 0.0
        s10 = 0.0
        s11 = 0.0
        capped = False
        opened = False
        for p in range(n_pairs):
            b0 = branch[0, p, 0]
            b1 = branch[0, p, 1]
            ob0 = old_branch[c, p, 0]
            ob1 = old_branch[c, p, 1]
            mid0 = 0.5 * (ob0 + b0)
            mid1 = 0.5 * (ob1 + b1)
            norm = math.sqrt(mid0 * mid0 + mid1 * mid1)
            trial = (shear[c, p] if old_contact[c, p] else 0.0) + kt * (
                (b0 - ob0) * -(mid1 / norm) + (b1 - ob1) * (mid0 / norm))
            f_n = fn[0, p]
            cap = mu * f_n
            touching = contact[0, p]
            fs = min(max(trial, -cap), cap) if touching else 0.0
            new_shear[c, p] = fs
            capped = capped or (touching and abs(trial) > cap)
            opened = opened or (old_fn[c, p] > 0.0 and f_n == 0.0)
            f0 = -f_n * u[p, 0] + fs * -u[p, 1]
            f1 = -f_n * u[p, 1] + fs * u[p, 0]
            s00 += f0 * b0
            s01 += f0 * b1
            s10 += f1 * b0
            s11 += f1 * b1
        moment[c, 0, 0] = -s00
        moment[c, 0, 1] = -s01
        moment[c, 1, 0] = -s10
        moment[c, 1, 1] = -s11
        twice = 0.0
        for k in range(n_outer):
            i = outer[k]
            j = outer[(k + 1) % n_outer]
            twice += x[i, 0] * x[j, 1] - x[j, 0] * x[i, 1]
        area[c] = 0.5 * abs(twice)
        capped_any[c] = capped
        opened_any[c] = opened


class FastIncrement(NamedTuple):
    """Outcome of ``FastAdvance.__call__`` (numpy, first axis n_cells).

    cell_size (n, 2) [m], free_position (n, n_free) [m], shear_force (n, n_pairs) [N]: the new
    state; moment (n, 2, 2) [N m] (compression positive); area (n,) [m^2]; capped, opened:
    bool (n,), a Coulomb cap / the no-tension branch acted on some pair of the cell.
    """

    cell_size: np.ndarray
    free_position: np.ndarray
    shear_force: np.ndarray
    moment: np.ndarray
    area: np.ndarray
    capped: np.ndarray
    opened: np.ndarray


class FastAdvance:
    """``MesoNet.advance`` for inference on CPU: numba physics (float64) around one MLP call.

    Args:
        net: the trained network (its schema, active pairs, normalisation and layers are copied).
        mlp_dtype: torch dtype of the perceptron's arithmetic (float32 or float64).
    """

    def __init__(self, net: MesoNet, mlp_dtype: torch.dtype = torch.float64) -> None:
        schema = net.schema
        as_np = lambda t, dtype=np.float64: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)  # noqa: E731
        self.frac = as_np(schema.driven_fraction)
        self.free_dofs = as_np(schema.free_dofs, np.int64)
        self.pairs = as_np(schema.pairs, np.int64)
        self.radius = as_np(schema.radius)
        self.outer = as_np(schema.outer, np.int64)
        self.active = as_np(net.active_index, np.int64)
        self.feature_mean = as_np(net.feature_mean)
        self.feature_std = as_np(net.feature_std)
        self.rate_mean = as_np(net.rate_mean)
        self.rate_std = as_np(net.rate_std)
        self.diameter, self.kn, self.kt, self.mu = schema.diameter, schema.kn, schema.kt, schema.mu
        self.tol = schema.contact_tolerance
        self.mlp_dtype = mlp_dtype
        linears = [layer for layer in net.mlp if isinstance(layer, torch.nn.Linear)]
        self.layers = [(lin.weight.detach().cpu().to(mlp_dtype).t().contiguous(),
                        lin.bias.detach().cpu().to(mlp_dtype).contiguous()) for lin in linears]
        self.np_dtype = {torch.float32: np.float32, torch.float64: np.float64}[mlp_dtype]

    def _mlp(self, feats: np.ndarray) -> np.ndarray:
        h = torch.from_numpy(feats)
        last = len(self.layers) - 1
        with torch.inference_mode():
            for k, (weight, bias) in enumerate(self.layers):
                h = torch.addmm(bias, h, weight)
                if k < last:
                    h = torch.tanh_(h)
        return h.numpy()

    def __call__(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                 d_eps: np.ndarray) -> FastIncrement:
        """One increment of every cell: state (n, 2), (n, n_free), (n, n_pairs) and probe (n, 2) [-]."""
        size = np.ascontiguousarray(cell_size, dtype=np.float64)
        free = np.ascontiguousarray(free_position, dtype=np.float64)
        shear = np.ascontiguousarray(shear_force, dtype=np.float64)
        d_eps = np.ascontiguousarray(d_eps, dtype=np.float64)
        n, n_free, n_pairs = size.shape[0], self.free_dofs.shape[0], self.pairs.shape[0]
        feats = np.empty((n, self.feature_mean.shape[0]), dtype=self.np_dtype)
        m = np.empty(n)
        unbalanced = np.empty((n, n_free))
        old_branch = np.empty((n, n_pairs, 2))
        old_contact = np.empty((n, n_pairs), dtype=np.bool_)
        old_fn = np.empty((n, n_pairs))
        _features(size, free, shear, d_eps, self.frac, self.free_dofs, self.pairs, self.radius, self.active,
                  self.feature_mean, self.feature_std, self.diameter, self.kn, self.mu, self.tol, GAP_CLIP,
                  feats, m, unbalanced, old_branch, old_contact, old_fn)
        out = self._mlp(feats)
        result = FastIncrement(np.empty_like(size), np.empty_like(free), np.empty_like(shear), np.empty((n, 2, 2)),
                               np.empty(n), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_))
        _advance(size, free, shear, d_eps, out, m, unbalanced, old_branch, old_contact, old_fn, self.frac,
                 self.free_dofs, self.pairs, self.radius, self.outer, self.rate_mean, self.rate_std,
                 COMPLIANCE_SCALE, self.diameter, self.kn, self.kt, self.mu, self.tol, RELAXATION_RAMP, *result)
        return result
