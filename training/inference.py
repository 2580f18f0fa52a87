"""Fast no-autograd inference of ``MesoNet.advance``: compiled cell physics around one MLP call.

``FastAdvance`` gives the same increment as ``MesoNet.advance`` (``training.network``,
``training.cell_physics``) up to float rounding, for inference only (no autograd):

1. ``_features`` (numba, float64, loops over cells innermost so that they vectorise):
   positions, contacts, pair forces, unbalanced forces and the z-scored features of the
   state before the increment;
2. the multilayer perceptron (numpy/BLAS; hidden layers float32, output layer float64), on
   fixed blocks of ``MLP_BLOCK`` cells;
3. ``_advance`` (numba, float64): the free-DOF displacement from the network output, the
   new state by the contact law, its Love-Weber moment, area and contact-law branch flags.

The features are z-scored in float64 before the cast to float32, the output layer and the
un-normalisation are float64, so float32 only rounds the hidden layers' arithmetic (its
effect on whole runs is measured in ``docs/ann.md``). Every block of cells goes through
BLAS calls of one shape, so a cell's result is bit-identical whatever batch it is in (the
cell contract's batch invariance). The physics stays float64 (positions must be resolved to
~1e-7 D). The tangent (autograd) uses ``MesoNet.advance``.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch

from training.network import COMPLIANCE_SCALE, GAP_CLIP, RELAXATION_RAMP, MesoNet

MLP_BLOCK = 64
"""Cells per perceptron block: the batch is padded to a multiple of it [-]."""


@numba.njit(cache=True, error_model="numpy")
def _positions(size, free, frac, free_dofs, x):
    """Grain centres into ``x`` (n_grains, 2, n) [m]: driven from ``size`` (2, n), free from ``free`` (n_free, n)."""
    n = size.shape[1]
    for g in range(frac.shape[0]):
        for a in range(2):
            row, scale, size_a = x[g, a], frac[g, a], size[a]
            for c in range(n):
                row[c] = scale * size_a[c]
    for k in range(free_dofs.shape[0]):
        row, free_k = x[free_dofs[k, 0], free_dofs[k, 1]], free[k]
        for c in range(n):
            row[c] = free_k[c]


@numba.njit(cache=True, error_model="numpy")
def _z_score(values, mean, std, feats_row):
    """``feats_row`` (n,) = (values - mean) * (1 / std): a z-scored feature of every cell."""
    inv_std = 1.0 / std
    for c in range(values.shape[0]):
        feats_row[c] = (values[c] - mean) * inv_std


@numba.njit(cache=True, error_model="numpy")
def _features(size, free, shear, d_eps, frac, free_dofs, pairs, radius, active_slot, feature_mean, feature_std,
              diameter, kn, mu, tol, gap_clip, feats, m_out, unbalanced, old_branch, old_contact, old_fn):
    """Z-scored features, |d_eps|, unbalanced forces and the contacts of every cell before its increment.

    Cells are the LAST axis of every array: size (2, n), free (n_free, n), shear (n_pairs, n),
    d_eps (2, n); outputs feats (n_features, n_pad >= n) (any float dtype), m_out (n,),
    unbalanced (n_free, n) [N], old_branch (n_pairs, 2, n) [m], old_contact (n_pairs, n)
    bool, old_fn (n_pairs, n) [N]. ``active_slot[p]`` is the rank of pair p among the active
    pairs, -1 if inactive. Feature order: ``training.network.features_and_contacts``. Each
    loop over cells (innermost) touches few arrays, so that the compiler vectorises it.
    """
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    force_scale = kn * diameter
    x = np.empty((frac.shape[0], 2, n))
    net = np.zeros((frac.shape[0], 2, n))
    _positions(size, free, frac, free_dofs, x)
    dist, u0, u1, fs, value = np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    base = 4 + 2 * n_free
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        j = pairs[p, 1]
        rsum = radius[i] + radius[j]
        reach = rsum * (1.0 + tol)
        b0, b1, contact, fn, shear_p = old_branch[p, 0], old_branch[p, 1], old_contact[p], old_fn[p], shear[p]
        xi0, xi1, xj0, xj1 = x[i, 0], x[i, 1], x[j, 0], x[j, 1]
        for c in range(n):
            b0[c] = xj0[c] - xi0[c]
        for c in range(n):
            b1[c] = xj1[c] - xi1[c]
        for c in range(n):
            dist[c] = math.sqrt(b0[c] * b0[c] + b1[c] * b1[c])
        for c in range(n):
            contact[c] = dist[c] <= reach
        for c in range(n):
            fn[c] = kn * max(rsum - dist[c], 0.0) if contact[c] else 0.0
        for c in range(n):
            fs[c] = shear_p[c] if contact[c] else 0.0
        for c in range(n):
            u0[c] = b0[c] / dist[c]
        for c in range(n):
            u1[c] = b1[c] / dist[c]
        for c in range(n):
            value[c] = -fn[c] * u0[c] + fs[c] * -u1[c]
        net_i, net_j = net[i, 0], net[j, 0]
        for c in range(n):
            net_i[c] += value[c]
        for c in range(n):
            net_j[c] -= value[c]
        for c in range(n):
            value[c] = -fn[c] * u1[c] + fs[c] * u0[c]
        net_i, net_j = net[i, 1], net[j, 1]
        for c in range(n):
            net_i[c] += value[c]
        for c in range(n):
            net_j[c] -= value[c]
        slot = active_slot[p]
        if slot < 0:
            continue
        k0 = base + 6 * slot
        for c in range(n):
            value[c] = max((rsum - dist[c]) / diameter, -gap_clip)
        _z_score(value, feature_mean[k0], feature_std[k0], feats[k0])
        for c in range(n):
            value[c] = 1.0 if contact[c] else 0.0
        _z_score(value, feature_mean[k0 + 1], feature_std[k0 + 1], feats[k0 + 1])
        _z_score(u0, feature_mean[k0 + 2], feature_std[k0 + 2], feats[k0 + 2])
        _z_score(u1, feature_mean[k0 + 3], feature_std[k0 + 3], feats[k0 + 3])
        for c in range(n):
            value[c] = fs[c] / force_scale
        _z_score(value, feature_mean[k0 + 4], feature_std[k0 + 4], feats[k0 + 4])
        for c in range(n):
            value[c] = fs[c] / (mu * fn[c]) if fn[c] > 0 else 0.0
        _z_score(value, feature_mean[k0 + 5], feature_std[k0 + 5], feats[k0 + 5])
    for k in range(n_free):
        g = free_dofs[k, 0]
        a = free_dofs[k, 1]
        net_k, unbalanced_k, free_k, size_a = net[g, a], unbalanced[k], free[k], size[a]
        for c in range(n):
            unbalanced_k[c] = net_k[c]
        for c in range(n):
            value[c] = free_k[c] / diameter
        _z_score(value, feature_mean[4 + k], feature_std[4 + k], feats[4 + k])
        for c in range(n):
            value[c] = free_k[c] / size_a[c]
        _z_score(value, feature_mean[4 + n_free + k], feature_std[4 + n_free + k], feats[4 + n_free + k])
    d0, d1 = d_eps[0], d_eps[1]
    for c in range(n):
        m_out[c] = math.sqrt(d0[c] * d0[c] + d1[c] * d1[c])
    for a in range(2):
        d_a = d_eps[a]
        for c in range(n):
            value[c] = d_a[c] / m_out[c] if m_out[c] > 0 else 0.0
        _z_score(value, feature_mean[a], feature_std[a], feats[a])
        size_a = size[a]
        for c in range(n):
            value[c] = size_a[c] / diameter
        _z_score(value, feature_mean[2 + a], feature_std[2 + a], feats[2 + a])


@numba.njit(cache=True, error_model="numpy")
def _advance(size, free, shear, d_eps, out, m_in, unbalanced, old_branch, old_contact, old_fn, frac, free_dofs,
             pairs, radius, outer, rate_mean, rate_std, compliance_scale, diameter, kn, kt, mu, tol, ramp,
             new_size, new_free, new_shear, moment, area, capped_any, opened_any, mechanism, ramped, n_held):
    """Free-DOF displacement from the network output ``out`` (n_free + n_free^2, n_pad >= n), then the contact law.

    Cells are the last axis (``_features``). The rest rule of ``cell_physics.hold_at_rest``
    holds free grains with no contact at the start that nothing reaches. Outputs: the new
    state new_size (2, n), new_free (n_free, n), new_shear (n_pairs, n); the
    compression-positive moment (2, 2, n) [N m], the area (n,) [m^2], per-cell flags
    (bool (n,)): a trial tangential force exceeded mu f_n; a pair carrying a normal force
    opened; the moment is zero (mechanism); |d_eps| < ``ramp`` scaled the relaxation down;
    and n_held (n,) int64, the grains held at rest.
    """
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    n_grains = frac.shape[0]
    touched = np.zeros((n_grains, n), dtype=np.bool_)
    for p in range(pairs.shape[0]):
        contact, touched_i, touched_j = old_contact[p], touched[pairs[p, 0]], touched[pairs[p, 1]]
        for c in range(n):
            touched_i[c] |= contact[c]
        for c in range(n):
            touched_j[c] |= contact[c]
    d_free = np.empty((n_free, n))
    cf = np.empty(n)
    for k in range(n_free):
        cf[:] = 0.0
        for j in range(n_free):
            out_kj, unbalanced_j, eye = out[n_free + k * n_free + j], unbalanced[j], 1.0 if j == k else 0.0
            for c in range(n):
                cf[c] += compliance_scale * (eye + out_kj[c]) * unbalanced_j[c]
        out_k, d_free_k, std, mean = out[k], d_free[k], rate_std[k], rate_mean[k]
        for c in range(n):
            d_free_k[c] = diameter * m_in[c] * (out_k[c] * std + mean) - min(m_in[c] / ramp, 1.0) * (cf[c] / kn)
        touched_g, new_free_k, free_k = touched[free_dofs[k, 0]], new_free[k], free[k]
        for c in range(n):
            new_free_k[c] = free_k[c] + d_free_k[c] if touched_g[c] else free_k[c]
    for a in range(2):
        new_size_a, size_a, d_eps_a = new_size[a], size[a], d_eps[a]
        for c in range(n):
            new_size_a[c] = size_a[c] * (1.0 - d_eps_a[c])
    held = np.zeros((n_grains, n), dtype=np.bool_)
    for k in range(n_free):
        held_g, touched_g = held[free_dofs[k, 0]], touched[free_dofs[k, 0]]
        for c in range(n):
            held_g[c] = not touched_g[c]
    x = np.empty((n_grains, 2, n))
    for _ in range(n_grains):
        if not held.any():
            break
        _positions(new_size, new_free, frac, free_dofs, x)
        released = False
        for p in range(pairs.shape[0]):
            i = pairs[p, 0]
            j = pairs[p, 1]
            reach = (radius[i] + radius[j]) * (1.0 + tol)
            for c in range(n):
                if held[i, c] or held[j, c]:
                    b0 = x[j, 0, c] - x[i, 0, c]
                    b1 = x[j, 1, c] - x[i, 1, c]
                    if math.sqrt(b0 * b0 + b1 * b1) <= reach:
                        held[i, c] = False
                        held[j, c] = False
                        released = True
        if not released:
            break
        for k in range(n_free):
            g = free_dofs[k, 0]
            for c in range(n):
                new_free[k, c] = free[k, c] if held[g, c] else free[k, c] + d_free[k, c]
    n_held[:] = 0
    for g in range(n_grains):
        held_g = held[g]
        for c in range(n):
            n_held[c] += 1 if held_g[c] else 0
    _positions(new_size, new_free, frac, free_dofs, x)
    moment[:, :, :] = 0.0
    capped_any[:] = False
    opened_any[:] = False
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        j = pairs[p, 1]
        rsum = radius[i] + radius[j]
        reach = rsum * (1.0 + tol)
        for c in range(n):
            b0 = x[j, 0, c] - x[i, 0, c]
            b1 = x[j, 1, c] - x[i, 1, c]
            d = math.sqrt(b0 * b0 + b1 * b1)
            touching = d <= reach
            fn = kn * max(rsum - d, 0.0) if touching else 0.0
            ob0 = old_branch[p, 0, c]
            ob1 = old_branch[p, 1, c]
            mid0 = 0.5 * (ob0 + b0)
            mid1 = 0.5 * (ob1 + b1)
            norm = math.sqrt(mid0 * mid0 + mid1 * mid1)
            trial = (shear[p, c] if old_contact[p, c] else 0.0) + kt * (
                (b0 - ob0) * -(mid1 / norm) + (b1 - ob1) * (mid0 / norm))
            cap = mu * fn
            fs = min(max(trial, -cap), cap) if touching else 0.0
            new_shear[p, c] = fs
            capped_any[c] |= touching and abs(trial) > cap
            opened_any[c] |= old_fn[p, c] > 0.0 and fn == 0.0
            u0 = b0 / d
            u1 = b1 / d
            f0 = -fn * u0 + fs * -u1
            f1 = -fn * u1 + fs * u0
            moment[0, 0, c] -= f0 * b0
            moment[0, 1, c] -= f0 * b1
            moment[1, 0, c] -= f1 * b0
            moment[1, 1, c] -= f1 * b1
    n_outer = outer.shape[0]
    area[:] = 0.0
    for k in range(n_outer):
        i = outer[k]
        j = outer[(k + 1) % n_outer]
        xi0, xi1, xj0, xj1 = x[i, 0], x[i, 1], x[j, 0], x[j, 1]
        for c in range(n):
            area[c] += xi0[c] * xj1[c] - xj0[c] * xi1[c]
    for c in range(n):
        area[c] = 0.5 * abs(area[c])
        mechanism[c] = moment[0, 0, c] == 0.0 and moment[0, 1, c] == 0.0 and moment[1, 0, c] == 0.0 and \
            moment[1, 1, c] == 0.0
        ramped[c] = m_in[c] < ramp


class FastIncrement(NamedTuple):
    """Outcome of ``FastAdvance.__call__`` (numpy, first axis n_cells).

    cell_size (n, 2) [m], free_position (n, n_free) [m], shear_force (n, n_pairs) [N]: the new
    state; moment (n, 2, 2) [N m] (compression positive); area (n,) [m^2]; capped, opened:
    bool (n,), a Coulomb cap / the no-tension branch acted on some pair of the cell;
    mechanism: bool (n,), zero moment after the increment; relaxation_scaled: bool (n,),
    |d_eps| < ``RELAXATION_RAMP``; grains_held: int64 (n,), free grains held at rest
    (``training.cell_physics.hold_at_rest``).
    """

    cell_size: np.ndarray
    free_position: np.ndarray
    shear_force: np.ndarray
    moment: np.ndarray
    area: np.ndarray
    capped: np.ndarray
    opened: np.ndarray
    mechanism: np.ndarray
    relaxation_scaled: np.ndarray
    grains_held: np.ndarray


class FastAdvance:
    """``MesoNet.advance`` for inference on CPU: numba physics (float64) around the perceptron (float32 hidden layers).

    The perceptron runs on fixed blocks of ``MLP_BLOCK`` cells (the batch is padded to whole
    blocks), one BLAS call of the same shape per block and layer, so that a cell's result
    does not depend on the size of its batch or its place in it.

    Args:
        net: the trained network (its schema, active pairs, normalisation and layers are copied).
    """

    def __init__(self, net: MesoNet) -> None:
        schema = net.schema
        as_np = lambda t, dtype=np.float64: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)  # noqa: E731
        self.frac = as_np(schema.driven_fraction)
        self.free_dofs = as_np(schema.free_dofs, np.int64)
        self.pairs = as_np(schema.pairs, np.int64)
        self.radius = as_np(schema.radius)
        self.outer = as_np(schema.outer, np.int64)
        self.active_slot = np.full(self.pairs.shape[0], -1, dtype=np.int64)
        self.active_slot[as_np(net.active_index, np.int64)] = np.arange(int(net.active_index.shape[0]))
        self.feature_mean = as_np(net.feature_mean)
        self.feature_std = as_np(net.feature_std)
        self.rate_mean = as_np(net.rate_mean)
        self.rate_std = as_np(net.rate_std)
        self.diameter, self.kn, self.kt, self.mu = schema.diameter, schema.kn, schema.kt, schema.mu
        self.tol = schema.contact_tolerance
        linears = [layer for layer in net.mlp if isinstance(layer, torch.nn.Linear)]
        self.layers = [self._affine(as_np(lin.weight), as_np(lin.bias), lin is not linears[-1]) for lin in linears]

    @staticmethod
    def _affine(weight: np.ndarray, bias: np.ndarray, hidden: bool) -> np.ndarray:
        """[W | b] acting on inputs that end with a row of ones: float32 for a hidden layer, which also
        passes the ones on; float64 for the output layer."""
        affine = np.concatenate([weight, bias[:, None]], axis=1)
        if not hidden:
            return np.ascontiguousarray(affine)
        affine = np.concatenate([affine, np.eye(1, affine.shape[1], affine.shape[1] - 1)])
        return np.ascontiguousarray(affine, dtype=np.float32)

    def _mlp(self, feats: np.ndarray) -> np.ndarray:
        """Network output (n_outputs, n_pad) of z-scored features (n_features + 1, n_pad) ending with a row of ones.

        Cells along the columns, n_pad a multiple of ``MLP_BLOCK``: [W | b] [h; 1] per block of
        ``MLP_BLOCK`` columns; the hidden layers (float32) carry the row of ones along; the
        output layer is float64 (rounding the outputs to float32 tripled the largest error of
        the drained test at alpha0 = 40 deg, p0 = 2e5, ``docs/ann.md``).
        """
        n_pad = feats.shape[1]
        h = feats.reshape(feats.shape[0], n_pad // MLP_BLOCK, MLP_BLOCK).transpose(1, 0, 2)
        for affine in self.layers[:-1]:
            h = np.matmul(affine, h)
            np.tanh(h[:, :-1], out=h[:, :-1])
        out = np.matmul(self.layers[-1], h.astype(np.float64))
        return out.transpose(1, 0, 2).reshape(out.shape[1], n_pad)

    def __call__(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                 d_eps: np.ndarray) -> FastIncrement:
        """One increment of every cell: state (n, 2), (n, n_free), (n, n_pairs) and probe (n, 2) [-]."""
        size, free, shear, d_eps = (np.ascontiguousarray(np.asarray(a, dtype=np.float64).T)
                                    for a in (cell_size, free_position, shear_force, d_eps))
        n, n_free, n_pairs = size.shape[1], self.free_dofs.shape[0], self.pairs.shape[0]
        feats = np.zeros((self.feature_mean.shape[0] + 1, -(-n // MLP_BLOCK) * MLP_BLOCK), dtype=np.float32)
        feats[-1] = 1.0
        m = np.empty(n)
        unbalanced = np.empty((n_free, n))
        old_branch = np.empty((n_pairs, 2, n))
        old_contact = np.empty((n_pairs, n), dtype=np.bool_)
        old_fn = np.empty((n_pairs, n))
        _features(size, free, shear, d_eps, self.frac, self.free_dofs, self.pairs, self.radius, self.active_slot,
                  self.feature_mean, self.feature_std, self.diameter, self.kn, self.mu, self.tol, GAP_CLIP,
                  feats, m, unbalanced, old_branch, old_contact, old_fn)
        out = self._mlp(feats)
        new_size, new_free, new_shear = np.empty_like(size), np.empty_like(free), np.empty_like(shear)
        moment, area = np.empty((2, 2, n)), np.empty(n)
        flags = np.empty((4, n), dtype=np.bool_)
        n_held = np.empty(n, dtype=np.int64)
        _advance(size, free, shear, d_eps, out, m, unbalanced, old_branch, old_contact, old_fn, self.frac,
                 self.free_dofs, self.pairs, self.radius, self.outer, self.rate_mean, self.rate_std,
                 COMPLIANCE_SCALE, self.diameter, self.kn, self.kt, self.mu, self.tol, RELAXATION_RAMP,
                 new_size, new_free, new_shear, moment, area, *flags, n_held)
        return FastIncrement(np.ascontiguousarray(new_size.T), np.ascontiguousarray(new_free.T),
                             np.ascontiguousarray(new_shear.T), np.ascontiguousarray(moment.transpose(2, 0, 1)),
                             area, *flags, n_held)
