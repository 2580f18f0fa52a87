"""The features of the meso-ANN's input, compiled (numba, float64): the state before the increment.

Positions, contacts, pair forces, unbalanced forces and the z-scored features of every cell,
exactly as ``training.network`` computes them with torch; the features are z-scored in
float64 before the cast to float32 (the ratio f_s / (mu f_n), bounded by one, is divided in
float32). A pair that no cell has within reach is skipped after a square-root-free test, which
changes no bit of the result. Layouts: ``training.fast_cells``.
"""

import math

import numba
import numpy as np

from training.fast_cells import grain_positions, normal_force, pair_branch


@numba.njit(cache=True, error_model="numpy")
def load_fractions(old_fn, active_slot, base, per_pair, feats, feature_mean, inv_std):
    """Z-scored load fraction f_n / max f_n of each active pair (0 in a force-free cell), written
    into the rows of ``feats`` after the ``base + per_pair n_active`` pair features (``per_pair`` = 6
    in a planar cell, 9 in a spatial one), where the network has them (``load_features``); nothing
    otherwise. ``old_fn`` (n_pairs, n) [N]."""
    n = old_fn.shape[1]
    n_active = 0
    for p in range(active_slot.shape[0]):
        n_active = max(n_active, active_slot[p] + 1)
    load_base = base + per_pair * n_active
    if feats.shape[0] <= load_base:
        return
    largest = np.zeros(n)
    for p in range(old_fn.shape[0]):
        fn = old_fn[p]
        for c in range(n):
            largest[c] = max(largest[c], fn[c])
    for p in range(old_fn.shape[0]):
        slot = active_slot[p]
        if slot < 0:
            continue
        fn = old_fn[p]
        row, mean, scale = feats[load_base + slot], feature_mean[load_base + slot], inv_std[load_base + slot]
        for c in range(n):
            row[c] = ((fn[c] / largest[c] if largest[c] > 0 else 0.0) - mean) * scale


@numba.njit(cache=True, error_model="numpy")
def features(size, free, shear, d_eps, cells, law, scaling, before):
    """Z-scored features, norm(d_eps), unbalanced forces and the contacts of every cell before its increment.

    Layouts and tables: ``training.fast_cells``; the outputs are the arrays of ``before``.
    Feature order: ``training.network.features_and_contacts``; the load fractions of the active
    pairs are written where ``before.feats`` has a row for them (a network with ``load_features``); each
    is z-scored in float64 with ``feature_mean``, ``feature_std`` before the cast. Each loop
    over cells (innermost) writes few arrays, so that the compiler vectorises it.
    """
    frac, free_dofs, free_slot, pairs, radius = cells.frac, cells.free_dofs, cells.free_slot, cells.pairs, cells.radius
    active_slot, diameter, kn, mu, tol, gap_clip = cells.active_slot, law.diameter, law.kn, law.mu, law.tol, law.gap_clip
    feature_mean, feature_std = scaling.feature_mean, scaling.feature_std
    feats, m_out, unbalanced, old_branch, old_contact, old_fn = (before.feats, before.m, before.unbalanced,
                                                               before.old_branch, before.old_contact, before.old_fn)
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    inv_diameter = 1.0 / diameter
    inv_force_scale = 1.0 / (kn * diameter)
    inv_std = 1.0 / feature_std
    x = np.empty((frac.shape[0], 2, n))
    unbalanced[:, :] = 0.0
    grain_positions(size, free, frac, free_dofs, x)
    dist, u0, u1, fs = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    base = 4 + 2 * n_free
    for p in range(pairs.shape[0]):
        b0, b1, contact, fn, shear_p = old_branch[p, 0], old_branch[p, 1], old_contact[p], old_fn[p], shear[p]
        i, j, rsum, reach, near = pair_branch(x, pairs, radius, tol, p, b0, b1)
        slot = active_slot[p]
        if not near:
            contact[:] = False
            fn[:] = 0.0
            fs[:] = 0.0
            if slot < 0:
                continue
        for c in range(n):
            d = math.sqrt(b0[c] * b0[c] + b1[c] * b1[c])
            inv = 1.0 / d
            dist[c] = d
            u0[c] = b0[c] * inv
            u1[c] = b1[c] * inv
        if near:
            for c in range(n):
                touching = dist[c] <= reach
                contact[c] = touching
                fn[c] = normal_force(rsum - dist[c], kn) if touching else 0.0
                fs[c] = shear_p[c] if touching else 0.0
            for k in (free_slot[i, 0], free_slot[j, 0]):
                if k >= 0:
                    net_k, sign = unbalanced[k], 1.0 if k == free_slot[i, 0] else -1.0
                    for c in range(n):
                        net_k[c] += sign * (-fn[c] * u0[c] + fs[c] * -u1[c])
            for k in (free_slot[i, 1], free_slot[j, 1]):
                if k >= 0:
                    net_k, sign = unbalanced[k], 1.0 if k == free_slot[i, 1] else -1.0
                    for c in range(n):
                        net_k[c] += sign * (-fn[c] * u1[c] + fs[c] * u0[c])
        if slot < 0:
            continue
        k = base + 6 * slot
        row, mean, scale = feats[k], feature_mean[k], inv_std[k]
        for c in range(n):
            row[c] = (max((rsum - dist[c]) * inv_diameter, -gap_clip) - mean) * scale
        row, mean, scale = feats[k + 1], feature_mean[k + 1], inv_std[k + 1]
        for c in range(n):
            row[c] = ((1.0 if contact[c] else 0.0) - mean) * scale
        row, mean, scale = feats[k + 2], feature_mean[k + 2], inv_std[k + 2]
        for c in range(n):
            row[c] = (u0[c] - mean) * scale
        row, mean, scale = feats[k + 3], feature_mean[k + 3], inv_std[k + 3]
        for c in range(n):
            row[c] = (u1[c] - mean) * scale
        row, mean, scale = feats[k + 4], feature_mean[k + 4], inv_std[k + 4]
        for c in range(n):
            row[c] = (fs[c] * inv_force_scale - mean) * scale
        row, mean, scale = feats[k + 5], feature_mean[k + 5], inv_std[k + 5]
        for c in range(n):
            ratio = np.float32(fs[c]) / np.float32(mu * fn[c]) if fn[c] > 0 else np.float32(0.0)
            row[c] = (ratio - mean) * scale
    load_fractions(old_fn, active_slot, base, 6, feats, feature_mean, inv_std)
    for k in range(n_free):
        g = free_dofs[k, 0]
        a = free_dofs[k, 1]
        free_k, size_a = free[k], size[a]
        row, mean, scale = feats[4 + k], feature_mean[4 + k], inv_std[4 + k]
        for c in range(n):
            row[c] = (free_k[c] * inv_diameter - mean) * scale
        row, mean, scale = feats[4 + n_free + k], feature_mean[4 + n_free + k], inv_std[4 + n_free + k]
        for c in range(n):
            row[c] = (free_k[c] / size_a[c] - mean) * scale
    probe = d_eps.reshape(2 * n)  # d_eps[c, a] = probe[2 c + a]: a constant stride, so that the loops vectorise
    for c in range(n):
        m_out[c] = math.sqrt(probe[2 * c] * probe[2 * c] + probe[2 * c + 1] * probe[2 * c + 1])
    for a in range(2):
        size_a = size[a]
        row, mean, scale = feats[a], feature_mean[a], inv_std[a]
        for c in range(n):
            row[c] = ((probe[2 * c + a] / m_out[c] if m_out[c] > 0 else 0.0) - mean) * scale
        row, mean, scale = feats[2 + a], feature_mean[2 + a], inv_std[2 + a]
        for c in range(n):
            row[c] = (size_a[c] * inv_diameter - mean) * scale
