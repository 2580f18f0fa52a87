"""The meso-ANN increment of spatial cells, compiled (numba, float64): features before, state after.

The spatial counterpart of ``training.fast_features`` and ``training.fast_increment``, the same
physics as ``training.cell_physics`` with dim = 3 (``advance``): the spring of every pair is a
vector in its tangent plane, carried into the new tangent plane (projected and rescaled to its
length), grown by kt times the relative displacement normal to the mid-increment branch and
capped at mu f_n along its own direction where longer by more than ``CAP_SLACK``; V_cell is the
volume of the outer triangles. The dimension-free steps are shared with the planar kernels:
grain positions (``fast_cells.grain_positions``), the load fractions, the free-DOF displacement,
the rest rule, the start of a contact pass, the reset of a pair out of reach, the moment sum and
the mechanism and ramp flags (``fast_increment``).

Layouts (cells LAST, one cell a vector lane, nothing reduced across cells): size (3, n) [m],
free (n_free, n) [m], shear (n_pairs, 3, n) [N]; d_eps (n, 3) [-]; ``before.old_branch``
(n_pairs, 3, n). Tables: ``training.fast_tables`` (``CellTables.outer`` holds the faces
(n_faces, 3)). Unit vectors are branch / length (a division, as the torch path), and a pair no
cell has within reach is skipped after a square-root-free test (``any_within3``), which changes
no bit. Sign convention: compression and contraction positive; local frame 0 = n, 1 = t1, 2 = t2.
"""

import math

import numba
import numpy as np

from training.fast_cells import carried_spring3, grain_positions, normal_force
from training.fast_features import load_fractions
from training.fast_increment import (branch_counts, free_displacement, hold_at_rest, moment_flags, open_far_pair,
                                     start_pass, subtract_outer_rows)
from training.perceptron import forward_layers
from warp_hcell.core.contact import CAP_SLACK

PAIR_WIDTH = 9
"""Features per active pair of a spatial cell (``training.network.PAIR_FEATURES_3D``)."""


@numba.njit(cache=True, error_model="numpy")
def _within_bound(reach):
    """The squared length [m^2] under which a branch may be within ``reach`` [m]: a margin of 1e-9 of reach covers
    the rounding of the square-root-free test (``fast_cells.any_within``)."""
    return (reach * (1.0 + 1e-9)) ** 2


@numba.njit(cache=True, error_model="numpy")
def any_within3(b0, b1, b2, reach):
    """Whether some cell's branch (b0, b1, b2) (n,) each may be within ``reach`` [m] (``_within_bound``)."""
    bound = _within_bound(reach)
    within = 0  # a count, not a flag: the loop then vectorises
    for c in range(b0.shape[0]):
        within += b0[c] * b0[c] + b1[c] * b1[c] + b2[c] * b2[c] <= bound
    return within > 0


@numba.njit(cache=True, error_model="numpy")
def _pair_reach(pairs, radius, tol, p):
    """(i, j, r_i + r_j [m], reach (r_i + r_j)(1 + tol) [m]) of pair p."""
    i = pairs[p, 0]
    j = pairs[p, 1]
    rsum = radius[i] + radius[j]
    return i, j, rsum, rsum * (1.0 + tol)


@numba.njit(cache=True, error_model="numpy")
def pair_near3(x, pairs, radius, tol, p):
    """``pair_branch3``'s (i, j, r_i + r_j [m], reach [m], whether some cell may be within reach) of pair p, the
    branches not stored (``any_within3``'s test on x_j - x_i, computed on the fly)."""
    i, j, rsum, reach = _pair_reach(pairs, radius, tol, p)
    bound = _within_bound(reach)
    i0, i1, i2, j0, j1, j2 = x[i, 0], x[i, 1], x[i, 2], x[j, 0], x[j, 1], x[j, 2]
    within = 0
    for c in range(i0.shape[0]):
        b0, b1, b2 = j0[c] - i0[c], j1[c] - i1[c], j2[c] - i2[c]
        within += b0 * b0 + b1 * b1 + b2 * b2 <= bound
    return i, j, rsum, reach, within > 0


@numba.njit(cache=True, error_model="numpy")
def _difference(a, b, out):
    """out = a - b, rows (n,) [m]: a loop that vectorises."""
    for c in range(out.shape[0]):
        out[c] = a[c] - b[c]


@numba.njit(cache=True, error_model="numpy")
def store_branch3(x, i, j, b0, b1, b2):
    """The branch x_j - x_i of grains i, j at the centres x (n_grains, 3, n) [m] into b0, b1, b2 (n,) [m]."""
    _difference(x[j, 0], x[i, 0], b0)
    _difference(x[j, 1], x[i, 1], b1)
    _difference(x[j, 2], x[i, 2], b2)


@numba.njit(cache=True, error_model="numpy")
def pair_branch3(x, pairs, radius, tol, p, b0, b1, b2):
    """Pair p = (i, j) at the grain centres x (n_grains, 3, n) [m]: writes its branch x_j - x_i into
    b0, b1, b2 (n,) [m] and returns (i, j, r_i + r_j [m], reach (r_i + r_j)(1 + tol) [m], whether some
    cell may be within reach)."""
    i, j, rsum, reach = _pair_reach(pairs, radius, tol, p)
    store_branch3(x, i, j, b0, b1, b2)
    return i, j, rsum, reach, any_within3(b0, b1, b2, reach)


@numba.njit(cache=True, error_model="numpy")
def _zscore(row, values, mean, inv_std):
    """row (n,) float32 = (values - mean) * inv_std, in float64 before the cast."""
    for c in range(row.shape[0]):
        row[c] = (values[c] - mean) * inv_std


@numba.njit(cache=True, error_model="numpy")
def unit_branch(b, dist, u):
    """The length dist (n,) [m] and the unit vector u (3, n) of the branches b (3, n) [m] (one pass: it vectorises)."""
    for c in range(dist.shape[0]):
        d = math.sqrt(b[0, c] * b[0, c] + b[1, c] * b[1, c] + b[2, c] * b[2, c])
        dist[c] = d
        u[0, c] = b[0, c] / d
        u[1, c] = b[1, c] / d
        u[2, c] = b[2, c] / d


@numba.njit(cache=True, error_model="numpy")
def pair_features(dist, contact, u, fs, fn, rsum, diameter, gap_clip, force_scale, mu, rows, mean, inv_std):
    """The ``PAIR_WIDTH`` z-scored features of one active pair into rows (PAIR_WIDTH, n) float32 (``features3d``'s
    order), from its branch length dist and unit vector u (3, n), contact flag, spring fs (3, n) [N] and normal
    force fn [N]; each a value in float64, z-scored with ``mean`` and ``inv_std`` (PAIR_WIDTH,), then cast, in
    one pass per feature."""
    n = dist.shape[0]
    row, m, s = rows[0], mean[0], inv_std[0]
    for c in range(n):
        row[c] = (max((rsum - dist[c]) / diameter, -gap_clip) - m) * s
    row, m, s = rows[1], mean[1], inv_std[1]
    for c in range(n):
        row[c] = ((1.0 if contact[c] else 0.0) - m) * s
    for a in range(3):
        _zscore(rows[2 + a], u[a], mean[2 + a], inv_std[2 + a])
    for a in range(3):
        row, m, s, fs_a = rows[5 + a], mean[5 + a], inv_std[5 + a], fs[a]
        for c in range(n):
            row[c] = (fs_a[c] / force_scale - m) * s
    row, m, s = rows[8], mean[8], inv_std[8]
    for c in range(n):
        size_c = math.sqrt(fs[0, c] * fs[0, c] + fs[1, c] * fs[1, c] + fs[2, c] * fs[2, c])
        row[c] = ((size_c / (mu * fn[c]) if fn[c] > 0 else 0.0) - m) * s


@numba.njit(cache=True, error_model="numpy")
def features3d(size, free, shear, d_eps, cells, law, scaling, before):
    """Z-scored features, norm(d_eps), unbalanced forces and contacts of every spatial cell before its increment.

    Feature order: ``training.network.features_and_contacts`` (probe direction (3), l / D (3), free
    coordinates / D and / l, per active pair overlap / D, contact flag, branch direction (3), spring
    / (kn D) (3) and ``abs(f_s) / (mu f_n)``, then the load fractions where ``before.feats`` has rows for
    them); every feature z-scored in float64 before the cast to float32.
    """
    frac, free_dofs, free_slot, pairs, radius = cells.frac, cells.free_dofs, cells.free_slot, cells.pairs, cells.radius
    active_slot, diameter, kn, mu, tol, gap_clip = cells.active_slot, law.diameter, law.kn, law.mu, law.tol, law.gap_clip
    feature_mean, inv_std = scaling.feature_mean, 1.0 / scaling.feature_std
    feats, m_out, unbalanced, old_branch, old_contact, old_fn = (before.feats, before.m, before.unbalanced,
                                                               before.old_branch, before.old_contact, before.old_fn)
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    force_scale = kn * diameter
    x = np.empty((frac.shape[0], 3, n))
    unbalanced[:, :] = 0.0
    grain_positions(size, free, frac, free_dofs, x)
    dist, u, fs, value = np.empty(n), np.empty((3, n)), np.empty((3, n)), np.empty(n)
    base = 6 + 2 * n_free
    for p in range(pairs.shape[0]):
        b, contact, fn = old_branch[p], old_contact[p], old_fn[p]
        i, j, rsum, reach, near = pair_branch3(x, pairs, radius, tol, p, b[0], b[1], b[2])
        slot = active_slot[p]
        if not near:
            contact[:] = False
            fn[:] = 0.0
            if slot < 0:
                continue
            fs[:, :] = 0.0
        unit_branch(b, dist, u)
        if near:
            for c in range(n):
                touching = dist[c] <= reach
                contact[c] = touching
                fn[c] = normal_force(rsum - dist[c], kn) if touching else 0.0
            shear_p = shear[p]
            for c in range(n):
                stuck = contact[c]
                fs[0, c] = shear_p[0, c] if stuck else 0.0
                fs[1, c] = shear_p[1, c] if stuck else 0.0
                fs[2, c] = shear_p[2, c] if stuck else 0.0
            for a in range(3):
                fs_a, u_a = fs[a], u[a]
                for k in (free_slot[i, a], free_slot[j, a]):
                    if k >= 0:
                        net_k, sign = unbalanced[k], 1.0 if k == free_slot[i, a] else -1.0
                        for c in range(n):
                            net_k[c] += sign * (-fn[c] * u_a[c] + fs_a[c])
        if slot < 0:
            continue
        k = base + PAIR_WIDTH * slot
        pair_features(dist, contact, u, fs, fn, rsum, diameter, gap_clip, force_scale, mu, feats[k:k + PAIR_WIDTH],
                      feature_mean[k:k + PAIR_WIDTH], inv_std[k:k + PAIR_WIDTH])
    load_fractions(old_fn, active_slot, base, PAIR_WIDTH, feats, feature_mean, inv_std)
    for k in range(n_free):
        free_k, size_a = free[k], size[free_dofs[k, 1]]
        for c in range(n):
            value[c] = free_k[c] / diameter
        _zscore(feats[6 + k], value, feature_mean[6 + k], inv_std[6 + k])
        for c in range(n):
            value[c] = free_k[c] / size_a[c]
        _zscore(feats[6 + n_free + k], value, feature_mean[6 + n_free + k], inv_std[6 + n_free + k])
    for c in range(n):
        m_out[c] = math.sqrt(d_eps[c, 0] * d_eps[c, 0] + d_eps[c, 1] * d_eps[c, 1] + d_eps[c, 2] * d_eps[c, 2])
    for a in range(3):
        for c in range(n):
            value[c] = d_eps[c, a] / m_out[c] if m_out[c] > 0 else 0.0
        _zscore(feats[a], value, feature_mean[a], inv_std[a])
        size_a = size[a]
        for c in range(n):
            value[c] = size_a[c] / diameter
        _zscore(feats[3 + a], value, feature_mean[3 + a], inv_std[3 + a])


@numba.njit(cache=True, error_model="numpy", inline="always")
def pair_force3(b0, b1, b2, ob0, ob1, ob2, stuck, s0, s1, s2, rsum, reach, kn, kt, mu, slack):
    """One spatial contact after an increment, the compiled runtime's copy of the spatial contact law
    (``warp_hcell.dem.contact``): branch (b0, b1, b2) [m] at the end, (ob0, ob1, ob2) at the start; the
    pair touches where the branch length d <= ``reach`` [m], with normal force kn max(rsum - d, 0) [N];
    the old spring (s0, s1, s2) [N], counted only where ``stuck``, is turned into the new tangent plane,
    grows by kt times the tangential change of the branch and is capped at mu fn once it exceeds the
    cap by the factor ``slack``. Returns (touching, fn, u0, u1, u2, f0, f1, f2, trial, cap): the unit
    normal u, the tangential force f [N], the trial magnitude and the cap [N]."""
    d = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
    touching = d <= reach
    fn = normal_force(rsum - d, kn) if touching else 0.0
    u0, u1, u2 = b0 / d, b1 / d, b2 / d
    mid0, mid1, mid2 = 0.5 * (ob0 + b0), 0.5 * (ob1 + b1), 0.5 * (ob2 + b2)
    mid_norm = math.sqrt(mid0 * mid0 + mid1 * mid1 + mid2 * mid2)
    mid0, mid1, mid2 = mid0 / mid_norm, mid1 / mid_norm, mid2 / mid_norm
    r0, r1, r2 = b0 - ob0, b1 - ob1, b2 - ob2
    if stuck:
        s0, s1, s2 = carried_spring3(s0, s1, s2, u0, u1, u2)
    else:
        s0, s1, s2 = 0.0, 0.0, 0.0
    along = r0 * mid0 + r1 * mid1 + r2 * mid2
    t0 = s0 + kt * (r0 - along * mid0)
    t1 = s1 + kt * (r1 - along * mid1)
    t2 = s2 + kt * (r2 - along * mid2)
    trial = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    cap = mu * fn
    f0, f1, f2 = 0.0, 0.0, 0.0
    if touching:
        scale = cap / (trial if trial > 0 else 1.0) if trial > cap * slack else 1.0
        f0, f1, f2 = t0 * scale, t1 * scale, t2 * scale
    return touching, fn, u0, u1, u2, f0, f1, f2, trial, cap


@numba.njit(cache=True, error_model="numpy")
def pair_pass3(branch, old_branch, stuck, spring, old_fn, rsum, reach, kn, kt, mu, slack, new_spring, force,
               capped_any, opened_any):
    """``pair_force3`` of one pair in every cell: branch, old_branch, spring (3, n) and stuck, old_fn (n,) at the
    start; writes new_spring and the force on grain i, force (3, n) [N], and raises the flags capped_any, opened_any
    (n,). Rows of one pair, in a function of their own: the loop vectorises."""
    for c in range(branch.shape[1]):
        touching, fn, u0, u1, u2, f0, f1, f2, trial, cap = pair_force3(
            branch[0, c], branch[1, c], branch[2, c], old_branch[0, c], old_branch[1, c], old_branch[2, c], stuck[c],
            spring[0, c], spring[1, c], spring[2, c], rsum, reach, kn, kt, mu, slack)
        new_spring[0, c] = f0
        new_spring[1, c] = f1
        new_spring[2, c] = f2
        capped_any[c] |= touching and trial > cap
        opened_any[c] |= old_fn[c] > 0.0 and fn == 0.0
        force[0, c] = -fn * u0 + f0
        force[1, c] = -fn * u1 + f1
        force[2, c] = -fn * u2 + f2


@numba.njit(cache=True, error_model="numpy")
def contact_pass3(x, shear, before, cells, law, new_shear, capped_any, opened_any):
    """The spatial contact law at the new grain centres x (n_grains, 3, n): writes new_shear (n_pairs, 3,
    n) and the flags capped_any, opened_any (n,); returns the compression-positive moment (3, 3, n) [N m]."""
    n = x.shape[2]
    pairs, radius = cells.pairs, cells.radius
    kn, kt, mu, tol = law.kn, law.kt, law.mu, law.tol
    old_branch, old_contact, old_fn = before.old_branch, before.old_contact, before.old_fn
    moment = start_pass(x, capped_any, opened_any)
    b, force = np.empty((3, n)), np.empty((3, n))
    slack = 1.0 + CAP_SLACK
    for p in range(pairs.shape[0]):
        i, j, rsum, reach, near = pair_near3(x, pairs, radius, tol, p)
        if not near:
            open_far_pair(p, old_fn, new_shear, opened_any)
            continue
        store_branch3(x, i, j, b[0], b[1], b[2])
        pair_pass3(b, old_branch[p], old_contact[p], shear[p], old_fn[p], rsum, reach, kn, kt, mu, slack, new_shear[p],
                   force, capped_any, opened_any)
        subtract_outer_rows(moment, force, b)
    return moment


@numba.njit(cache=True, error_model="numpy")
def volume_and_flags(x, moment, m_in, faces, ramp, volume, mechanism, ramped, moment_out):
    """The volume (n,) [m^3] enclosed by the triangles ``faces`` (n_faces, 3), abs(sum_f a . (b x c)) / 6,
    the mechanism and ramp flags (n,), and the moment copied cells first into moment_out (n, 3, 3)."""
    n = x.shape[2]
    volume[:] = 0.0
    for f in range(faces.shape[0]):
        xa, xb, xc = x[faces[f, 0]], x[faces[f, 1]], x[faces[f, 2]]
        for c in range(n):
            volume[c] += (xa[0, c] * (xb[1, c] * xc[2, c] - xb[2, c] * xc[1, c])
                          + xa[1, c] * (xb[2, c] * xc[0, c] - xb[0, c] * xc[2, c])
                          + xa[2, c] * (xb[0, c] * xc[1, c] - xb[1, c] * xc[0, c]))
    for c in range(n):
        volume[c] = abs(volume[c]) / 6.0
    moment_flags(moment, m_in, ramp, mechanism, ramped, moment_out)


@numba.njit(cache=True, error_model="numpy")
def advance3d(size, free, shear, d_eps, out, cells, law, scaling, before, result):
    """Free-DOF displacement from the network output ``out`` (n_free + n_free^2, n) float32, then
    ``physics3d``: fills ``result`` (``training.fast_tables.Advanced``, new_size (3, n), new_shear
    (n_pairs, 3, n), moment (n, 3, 3))."""
    physics3d(size, free, shear, d_eps, free_displacement(out, before.m, before.unbalanced, scaling, law), cells, law,
              before, result)


@numba.njit(cache=True, error_model="numpy")
def physics3d(size, free, shear, d_eps, d_free, cells, law, before, result):
    """Given the free-DOF displacement d_free (n_free, n) [m]: the rest rule, the spatial contact law,
    the volume and the flags into ``result`` (``advance3d``)."""
    x = hold_at_rest(size, free, d_eps, d_free, before.old_contact, cells, law.tol, result.new_size, result.new_free,
                     result.n_held, result.held_dof)
    moment = contact_pass3(x, shear, before, cells, law, result.new_shear, result.capped, result.opened)
    volume_and_flags(x, moment, before.m, cells.outer, law.ramp, result.area, result.mechanism, result.ramped,
                     result.moment)


@numba.njit(cache=True, error_model="numpy")
def step3d(size, free, shear, d_eps, cells, law, scaling, weights, biases, before, layers, result, counts):
    """One whole spatial increment in one call, as ``training.fast_increment.step`` for planar cells:
    ``features3d`` into ``before``, the perceptron (``training.perceptron.forward_layers``) into ``layers``,
    ``advance3d`` on ``layers[-1]`` into ``result`` and ``branch_counts`` into ``counts``; the same operations
    as these calls apart."""
    features3d(size, free, shear, d_eps, cells, law, scaling, before)
    forward_layers(weights, biases, before.feats, layers)
    advance3d(size, free, shear, d_eps, layers[-1], cells, law, scaling, before, result)
    branch_counts(result, counts)
