"""Fast inference of ``MesoNet.advance``: compiled cell physics around one MLP call, and its tangent.

``FastAdvance`` gives the same increment as ``MesoNet.advance`` (``training.network``,
``training.cell_physics``) up to float rounding, without torch:

1. ``_features`` (numba, float64, loops over cells innermost so that they vectorise):
   positions, contacts, pair forces, unbalanced forces and the z-scored features of the
   state before the increment;
2. the multilayer perceptron (``training.perceptron``: float32, one fixed sequence of fused
   multiply-adds per cell, no BLAS);
3. ``_advance`` (numba, float64): the free-DOF displacement from the network output, the
   new state by the contact law, its Love-Weber moment, area and contact-law branch flags;
4. on request, the consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t) by forward-mode
   differentiation of steps 1-3 (``_probe_feature_tangent``, ``FastAdvance._mlp_tangent``,
   ``_moment_tangent``), equal to torch autograd of ``MesoNet.advance`` up to the float32
   rounding of the network.

The features are computed and z-scored in float64 before the cast to float32 (the ratio
f_s / (mu f_n), bounded by one, is divided in float32); the un-normalisation of the outputs
and all the physics are float64 (positions must be resolved to ~1e-7 D), so float32 only
rounds the network's arithmetic (its effect on whole runs is measured in ``docs/ann.md``).
Every loop over cells is innermost, each cell one lane, and nothing reduces across cells,
so a cell's result is bit-identical whatever batch it is in, wherever it sits in it and
whatever the CPU's vector width (the cell contract's batch invariance). A pair that
no cell has within reach is skipped after a square-root-free test, which changes no bit of
the result. The state arrays returned are transposed views of cells-last arrays, so that
the next increment reads them without a copy.

Sign convention: compression and contraction positive; local frame index 0 = n, 1 = t.
"""

from __future__ import annotations

import math
import threading
from typing import NamedTuple

import numba
import numpy as np
import torch

from training.network import COMPLIANCE_SCALE, GAP_CLIP, RELAXATION_RAMP, MesoNet
from training.perceptron import Perceptron
from warp_hcell.core.contact import coulomb_cap, normal_force

_normal_force = numba.njit(cache=True, error_model="numpy")(normal_force)
_coulomb_cap = numba.njit(cache=True, error_model="numpy")(coulomb_cap)


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
def _any_within(b0, b1, reach):
    """Whether some cell's pair may be within ``reach`` [m] of branch (b0, b1) (n,) each: a test without
    square roots whose margin (1e-9 of reach) covers their rounding, so that False means out of
    contact in every cell exactly as ``sqrt(b0^2 + b1^2) <= reach`` would decide."""
    bound = (reach * (1.0 + 1e-9)) ** 2
    near = False
    for c in range(b0.shape[0]):
        near |= b0[c] * b0[c] + b1[c] * b1[c] <= bound
    return near


@numba.njit(cache=True, error_model="numpy")
def _features(size, free, shear, d_eps, frac, free_dofs, free_slot, pairs, radius, active_slot, feature_mean,
              feature_std, diameter, kn, mu, tol, gap_clip, feats, m_out, unbalanced, old_branch, old_contact, old_fn):
    """Z-scored features, ``|d_eps|``, unbalanced forces and the contacts of every cell before its increment.

    Cells are the LAST axis of every array but the probe: size (2, n), free (n_free, n),
    shear (n_pairs, n), d_eps (n, 2); outputs feats (n_features, n) float32, m_out (n,),
    unbalanced (n_free, n) [N], old_branch (n_pairs, 2, n) [m], old_contact (n_pairs, n)
    bool, old_fn (n_pairs, n) [N]. ``active_slot[p]`` is the rank of pair p among the active
    pairs, -1 if inactive; ``free_slot[g, a]`` the rank of DOF (g, a) among the free DOFs, -1
    if driven. Feature order: ``training.network.features_and_contacts``; each
    is z-scored in float64 with ``feature_mean``, ``feature_std`` before the cast. Each loop
    over cells (innermost) writes few arrays, so that the compiler vectorises it.
    """
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    inv_diameter = 1.0 / diameter
    inv_force_scale = 1.0 / (kn * diameter)
    inv_std = 1.0 / feature_std
    x = np.empty((frac.shape[0], 2, n))
    unbalanced[:, :] = 0.0
    _positions(size, free, frac, free_dofs, x)
    dist, u0, u1, fs = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
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
            b1[c] = xj1[c] - xi1[c]
        slot = active_slot[p]
        near = _any_within(b0, b1, reach)
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
                fn[c] = _normal_force(rsum - dist[c], kn) if touching else 0.0
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
    d0, d1 = d_eps[:, 0], d_eps[:, 1]
    for c in range(n):
        m_out[c] = math.sqrt(d0[c] * d0[c] + d1[c] * d1[c])
    for a in range(2):
        d_a, size_a = d_eps[:, a], size[a]
        row, mean, scale = feats[a], feature_mean[a], inv_std[a]
        for c in range(n):
            row[c] = ((d_a[c] / m_out[c] if m_out[c] > 0 else 0.0) - mean) * scale
        row, mean, scale = feats[2 + a], feature_mean[2 + a], inv_std[2 + a]
        for c in range(n):
            row[c] = (size_a[c] * inv_diameter - mean) * scale


@numba.njit(cache=True, error_model="numpy")
def _advance(size, free, shear, d_eps, out, m_in, unbalanced, old_branch, old_contact, old_fn, frac, free_dofs,
             pairs, radius, outer, rate_mean, rate_std, compliance_scale, diameter, kn, kt, mu, tol, ramp,
             new_size, new_free, new_shear, moment_out, area, capped_any, opened_any, mechanism, ramped, n_held,
             held_dof):
    """Free-DOF displacement from the network output ``out``, then the contact law.

    ``out`` (n_free + n_free^2, n) float32 is the perceptron's output, cells last.

    Array layouts as in ``_features``. The rest rule of ``cell_physics.hold_at_rest``
    holds free grains with no contact at the start that nothing reaches. Outputs: the new
    state new_size (2, n), new_free (n_free, n), new_shear (n_pairs, n); the
    compression-positive moment_out (n, 2, 2) [N m] (cells FIRST), the area (n,) [m^2], per-cell flags
    (bool (n,)): a trial tangential force exceeded mu f_n; a pair carrying a normal force
    opened; the moment is zero (mechanism); |d_eps| < ``ramp`` scaled the relaxation down;
    and n_held (n,) int64, the grains held at rest; held_dof (n_free, n) bool, the free DOFs
    of those grains.
    """
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    n_grains = frac.shape[0]
    moment = np.zeros((2, 2, n))
    touched = np.zeros((n_grains, n), dtype=np.bool_)
    for p in range(pairs.shape[0]):
        contact, touched_i, touched_j = old_contact[p], touched[pairs[p, 0]], touched[pairs[p, 1]]
        for c in range(n):
            touched_i[c] |= contact[c]
            touched_j[c] |= contact[c]
    d_free = np.empty((n_free, n))
    cf = np.empty(n)
    inv_kn, inv_ramp = 1.0 / kn, 1.0 / ramp
    for k in range(n_free):
        cf[:] = 0.0
        for j in range(n_free):
            out_kj, unbalanced_j, eye = out[n_free + k * n_free + j], unbalanced[j], 1.0 if j == k else 0.0
            for c in range(n):
                cf[c] += compliance_scale * (eye + out_kj[c]) * unbalanced_j[c]
        out_k, d_free_k, std, mean = out[k], d_free[k], rate_std[k], rate_mean[k]
        for c in range(n):
            d_free_k[c] = diameter * m_in[c] * (out_k[c] * std + mean) - min(m_in[c] * inv_ramp, 1.0) * (cf[c] * inv_kn)
    for k in range(n_free):
        touched_g, new_free_k, free_k, d_free_k = touched[free_dofs[k, 0]], new_free[k], free[k], d_free[k]
        for c in range(n):
            new_free_k[c] = free_k[c] + d_free_k[c] if touched_g[c] else free_k[c]
    for a in range(2):
        new_size_a, size_a, d_eps_a = new_size[a], size[a], d_eps[:, a]
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
    for k in range(n_free):
        held_dof[k] = held[free_dofs[k, 0]]
    n_held[:] = 0
    for g in range(n_grains):
        held_g = held[g]
        for c in range(n):
            n_held[c] += 1 if held_g[c] else 0
    _positions(new_size, new_free, frac, free_dofs, x)
    capped_any[:] = False
    opened_any[:] = False
    b0_p, b1_p = np.empty(n), np.empty(n)
    for p in range(pairs.shape[0]):
        i = pairs[p, 0]
        j = pairs[p, 1]
        rsum = radius[i] + radius[j]
        reach = rsum * (1.0 + tol)
        xi0, xi1, xj0, xj1 = x[i, 0], x[i, 1], x[j, 0], x[j, 1]
        for c in range(n):
            b0_p[c] = xj0[c] - xi0[c]
            b1_p[c] = xj1[c] - xi1[c]
        if not _any_within(b0_p, b1_p, reach):
            new_shear[p, :] = 0.0
            old_fn_p = old_fn[p]
            for c in range(n):
                opened_any[c] |= old_fn_p[c] > 0.0
            continue
        for c in range(n):
            b0 = b0_p[c]
            b1 = b1_p[c]
            d = math.sqrt(b0 * b0 + b1 * b1)
            touching = d <= reach
            fn = _normal_force(rsum - d, kn) if touching else 0.0
            ob0 = old_branch[p, 0, c]
            ob1 = old_branch[p, 1, c]
            mid0 = 0.5 * (ob0 + b0)
            mid1 = 0.5 * (ob1 + b1)
            inv_norm = 1.0 / math.sqrt(mid0 * mid0 + mid1 * mid1)
            trial = (shear[p, c] if old_contact[p, c] else 0.0) + kt * (
                (b0 - ob0) * -(mid1 * inv_norm) + (b1 - ob1) * (mid0 * inv_norm))
            fs = _coulomb_cap(trial, fn, mu) if touching else 0.0
            new_shear[p, c] = fs
            capped_any[c] |= touching and abs(trial) > mu * fn
            opened_any[c] |= old_fn[p, c] > 0.0 and fn == 0.0
            inv_d = 1.0 / d
            u0 = b0 * inv_d
            u1 = b1 * inv_d
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
    for c in range(n):
        for a in range(2):
            moment_out[c, a, 0] = moment[a, 0, c]
            moment_out[c, a, 1] = moment[a, 1, c]


@numba.njit(cache=True, error_model="numpy")
def _probe_feature_tangent(d_eps, m, feature_std, f_dot):
    """Derivative of the two z-scored probe-direction features with respect to d_eps.

    d_eps (n, 2), m = |d_eps| (n,); output f_dot (2, 2, n) float32: direction j, feature a (0,
    1), cell. d(d_a / m)/d(d_j) = (delta_aj - u_a u_j) / m; zero at m = 0, like the autograd
    path's masked division.
    """
    n = m.shape[0]
    f_dot[:] = 0.0
    for c in range(n):
        if m[c] > 0.0:
            u0, u1, inv_m = d_eps[c, 0] / m[c], d_eps[c, 1] / m[c], 1.0 / m[c]
            f_dot[0, 0, c] = (1.0 - u0 * u0) * inv_m / feature_std[0]
            f_dot[0, 1, c] = -u1 * u0 * inv_m / feature_std[1]
            f_dot[1, 0, c] = -u0 * u1 * inv_m / feature_std[0]
            f_dot[1, 1, c] = (1.0 - u1 * u1) * inv_m / feature_std[1]


@numba.njit(cache=True, error_model="numpy")
def _moment_tangent(size, free, d_eps, out, out_dot, m_in, unbalanced, old_branch, old_contact, frac, free_dofs,
                    pairs, radius, rate_mean, rate_std, compliance_scale, diameter, kn, kt, mu, tol, ramp, new_size,
                    new_free, shear, held_dof, tangent):
    """Consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t) [N m] of the increment ``_advance`` took: forward mode.

    Arrays as in ``_advance`` (its inputs, its new state new_size, new_free and held_dof);
    ``shear`` (n_pairs, n) is the tangential force before the increment; out_dot (2,
    n_outputs, n) the derivative of the network output along d_eps_n, d_eps_t
    (``FastAdvance._mlp_tangent``). Output tangent (n, 2, 2): [c, i, j] = d S_ii / d eps_j,
    compression positive. Branch choices (contact, Coulomb cap, held grains, relaxation ramp)
    are those of the increment, as autograd takes them; the derivative is zero where
    ``_advance`` puts a constant.
    """
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    n_grains = frac.shape[0]
    x = np.empty((n_grains, 2, n))
    _positions(new_size, new_free, frac, free_dofs, x)
    x_dot = np.empty((2, n_grains, 2, n))
    d_free_dot = np.empty((n_free, n))
    relax = np.zeros((n_free, n))  # C F of the increment (compliance times unbalanced force) [N]
    for k in range(n_free):
        for c in range(n):
            for q in range(n_free):
                relax[k, c] += compliance_scale * ((1.0 if q == k else 0.0) + out[n_free + k * n_free + q, c]) * \
                    unbalanced[q, c]
    tangent[:, :, :] = 0.0
    for j in range(2):
        for g in range(n_grains):
            for a in range(2):
                scale_a, size_a, row = frac[g, a], size[a], x_dot[j, g, a]
                for c in range(n):
                    row[c] = -scale_a * size_a[c] if a == j else 0.0
        for k in range(n_free):
            std, mean = rate_std[k], rate_mean[k]
            for c in range(n):
                relax_dot = 0.0
                for q in range(n_free):
                    relax_dot += compliance_scale * out_dot[j, n_free + k * n_free + q, c] * unbalanced[q, c]
                m = m_in[c]
                m_dot = d_eps[c, j] / m if m > 0.0 else 0.0
                ramp_factor = min(m / ramp, 1.0)
                ramp_dot = m_dot / ramp if m < ramp else 0.0
                value = diameter * (m_dot * (out[k, c] * std + mean) + m * out_dot[j, k, c] * std) - (
                    ramp_dot * relax[k, c] + ramp_factor * relax_dot) / kn
                d_free_dot[k, c] = 0.0 if held_dof[k, c] else value
            x_dot[j, free_dofs[k, 0], free_dofs[k, 1]] = d_free_dot[k]
    for p in range(pairs.shape[0]):
        i_g = pairs[p, 0]
        j_g = pairs[p, 1]
        rsum = radius[i_g] + radius[j_g]
        reach = rsum * (1.0 + tol)
        for c in range(n):
            b0 = x[j_g, 0, c] - x[i_g, 0, c]
            b1 = x[j_g, 1, c] - x[i_g, 1, c]
            d = math.sqrt(b0 * b0 + b1 * b1)
            if d > reach:
                continue
            fn = _normal_force(rsum - d, kn)
            ob0, ob1 = old_branch[p, 0, c], old_branch[p, 1, c]
            mid0, mid1 = 0.5 * (ob0 + b0), 0.5 * (ob1 + b1)
            norm = math.sqrt(mid0 * mid0 + mid1 * mid1)
            n0, n1 = mid0 / norm, mid1 / norm
            rel0, rel1 = b0 - ob0, b1 - ob1
            trial = (shear[p, c] if old_contact[p, c] else 0.0) + kt * (rel0 * -n1 + rel1 * n0)
            fs = _coulomb_cap(trial, fn, mu)
            cap = mu * fn
            u0, u1 = b0 / d, b1 / d
            f0 = -fn * u0 + fs * -u1
            f1 = -fn * u1 + fs * u0
            for j in range(2):
                db0 = x_dot[j, j_g, 0, c] - x_dot[j, i_g, 0, c]
                db1 = x_dot[j, j_g, 1, c] - x_dot[j, i_g, 1, c]
                d_dot = (b0 * db0 + b1 * db1) / d
                fn_dot = -kn * d_dot if rsum - d > 0.0 else 0.0
                proj = n0 * 0.5 * db0 + n1 * 0.5 * db1
                n0_dot, n1_dot = (0.5 * db0 - n0 * proj) / norm, (0.5 * db1 - n1 * proj) / norm
                trial_dot = kt * (db0 * -n1 + db1 * n0 + rel0 * -n1_dot + rel1 * n0_dot)
                if trial > cap:
                    fs_dot = mu * fn_dot
                elif trial < -cap:
                    fs_dot = -mu * fn_dot
                else:
                    fs_dot = trial_dot
                u0_dot, u1_dot = (db0 - u0 * d_dot) / d, (db1 - u1 * d_dot) / d
                f0_dot = -fn_dot * u0 - fn * u0_dot + fs_dot * -u1 + fs * -u1_dot
                f1_dot = -fn_dot * u1 - fn * u1_dot + fs_dot * u0 + fs * u0_dot
                tangent[c, 0, j] -= f0_dot * b0 + f0 * db0
                tangent[c, 1, j] -= f1_dot * b1 + f1 * db1


def _cells_last(values: np.ndarray) -> np.ndarray:
    """(k, n) float64 C-contiguous transpose of per-cell ``values`` (n, k); a view where the state came
    from ``FastAdvance`` (whose state arrays are views of cells-last arrays), a copy otherwise."""
    values = np.asarray(values)
    return values.T if values.dtype == np.float64 and values.T.flags.c_contiguous else np.ascontiguousarray(
        values.T, dtype=np.float64)


class FastIncrement(NamedTuple):
    """Outcome of ``FastAdvance.__call__`` (numpy, first axis n_cells).

    cell_size (n, 2) [m], free_position (n, n_free) [m], shear_force (n, n_pairs) [N]: the new
    state (transposed views of cells-last arrays, so that the next increment reads them
    without a copy); moment (n, 2, 2) [N m] (compression positive); area (n,) [m^2]; capped, opened:
    bool (n,), a Coulomb cap / the no-tension branch acted on some pair of the cell;
    mechanism: bool (n,), zero moment after the increment; relaxation_scaled: bool (n,),
    ``|d_eps|`` < ``RELAXATION_RAMP``; grains_held: int64 (n,), free grains held at rest
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


class _Workspace(NamedTuple):
    """Scratch arrays of one ``FastAdvance`` call (cells last, see ``_features``); ``layers``: each
    perceptron layer's output (width, n) float32."""

    feats: np.ndarray
    m: np.ndarray
    unbalanced: np.ndarray
    old_branch: np.ndarray
    old_contact: np.ndarray
    old_fn: np.ndarray
    layers: list


class FastAdvance:
    """``MesoNet.advance`` for inference on CPU: numba physics (float64) around the perceptron (float32).

    The perceptron is ``training.perceptron.Perceptron``: each cell's output is one fixed
    sequence of float32 operations, so a cell's result does not depend on the size of its
    batch, its place in it or the CPU's vector width. Scratch arrays are kept per thread
    between calls with the same number of cells; the arrays returned are new.

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
        self.free_slot = np.full(self.frac.shape, -1, dtype=np.int64)
        self.free_slot[self.free_dofs[:, 0], self.free_dofs[:, 1]] = np.arange(self.free_dofs.shape[0])
        self.active_slot = np.full(self.pairs.shape[0], -1, dtype=np.int64)
        self.active_slot[as_np(net.active_index, np.int64)] = np.arange(int(net.active_index.shape[0]))
        self.feature_mean = as_np(net.feature_mean)
        self.feature_std = as_np(net.feature_std)
        self.rate_mean = as_np(net.rate_mean)
        self.rate_std = as_np(net.rate_std)
        self.diameter, self.kn, self.kt, self.mu = schema.diameter, schema.kn, schema.kt, schema.mu
        self.tol = schema.contact_tolerance
        self.perceptron = Perceptron([(as_np(layer.weight), as_np(layer.bias))
                                      for layer in net.mlp if isinstance(layer, torch.nn.Linear)])
        self._local = threading.local()

    def _workspace(self, n: int) -> _Workspace:
        """This thread's scratch arrays for ``n`` cells (kept from its previous call with as many)."""
        work = getattr(self._local, "work", None)
        if work is None or work.m.shape[0] != n:
            n_free, n_pairs = self.free_dofs.shape[0], self.pairs.shape[0]
            work = _Workspace(np.empty((self.feature_mean.shape[0], n), dtype=np.float32), np.empty(n),
                              np.empty((n_free, n)), np.empty((n_pairs, 2, n)), np.empty((n_pairs, n), dtype=np.bool_),
                              np.empty((n_pairs, n)), self.perceptron.buffers(n))
            self._local.work = work
        return work

    def _mlp_tangent(self, work: _Workspace, f_dot: np.ndarray) -> np.ndarray:
        """Derivative of the network output along d_eps_n and d_eps_t, (2, n_outputs, n) float32, from
        that of the probe features ``f_dot`` (2, 2, n) (features 0 and 1, the only ones that depend on
        d_eps) and the activations the forward pass left in ``work.layers``."""
        return np.stack([self.perceptron.jvp(0, f_dot[j], work.layers) for j in range(2)])

    def __call__(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                 d_eps: np.ndarray) -> FastIncrement:
        """One increment of every cell: state (n, 2), (n, n_free), (n, n_pairs) and probe (n, 2) [-]."""
        return self.increment(cell_size, free_position, shear_force, d_eps)[0]

    def increment(self, cell_size: np.ndarray, free_position: np.ndarray, shear_force: np.ndarray,
                  d_eps: np.ndarray, with_tangent: bool = False) -> tuple[FastIncrement, np.ndarray | None]:
        """``__call__``, and with ``with_tangent`` also the consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t)
        [N m], (n, 2, 2), by forward-mode differentiation of the same increment (``_moment_tangent``)."""
        size, free, shear = (_cells_last(a) for a in (cell_size, free_position, shear_force))
        d_eps = np.asarray(d_eps, dtype=np.float64)
        n, n_free, n_pairs = size.shape[1], self.free_dofs.shape[0], self.pairs.shape[0]
        work = self._workspace(n)
        _features(size, free, shear, d_eps, self.frac, self.free_dofs, self.free_slot, self.pairs, self.radius,
                  self.active_slot, self.feature_mean, self.feature_std, self.diameter, self.kn, self.mu, self.tol,
                  GAP_CLIP, work.feats, work.m, work.unbalanced, work.old_branch, work.old_contact, work.old_fn)
        out = self.perceptron.forward(work.feats, work.layers)
        new_size, new_free, new_shear = np.empty((2, n)), np.empty((n_free, n)), np.empty((n_pairs, n))
        moment, area = np.empty((n, 2, 2)), np.empty(n)
        flags = np.empty((4, n), dtype=np.bool_)
        n_held = np.empty(n, dtype=np.int64)
        held_dof = np.empty((n_free, n), dtype=np.bool_)
        _advance(size, free, shear, d_eps, out, work.m, work.unbalanced, work.old_branch, work.old_contact,
                 work.old_fn, self.frac, self.free_dofs, self.pairs, self.radius, self.outer, self.rate_mean,
                 self.rate_std, COMPLIANCE_SCALE, self.diameter, self.kn, self.kt, self.mu, self.tol, RELAXATION_RAMP,
                 new_size, new_free, new_shear, moment, area, *flags, n_held, held_dof)
        tangent = None
        if with_tangent:
            f_dot = np.empty((2, 2, n), dtype=np.float32)
            _probe_feature_tangent(d_eps, work.m, self.feature_std, f_dot)
            out_dot = self._mlp_tangent(work, f_dot)
            tangent = np.empty((n, 2, 2))
            _moment_tangent(size, free, d_eps, out, out_dot, work.m, work.unbalanced, work.old_branch,
                            work.old_contact, self.frac, self.free_dofs, self.pairs, self.radius, self.rate_mean,
                            self.rate_std, COMPLIANCE_SCALE, self.diameter, self.kn, self.kt, self.mu, self.tol,
                            RELAXATION_RAMP, new_size, new_free, shear, held_dof, tangent)
        return FastIncrement(new_size.T, new_free.T, new_shear.T, moment, area, *flags, n_held), tangent
