"""The meso-ANN's increment, compiled (numba, float64): from the network output to the new state.

``advance`` composes the steps, each one job: the free-DOF displacement from the network output
(``free_displacement``), the DEM's rest rule (``hold_at_rest``, as
``training.cell_physics.hold_at_rest``), the contact law at the new positions
(``contact_pass``, ``warp_hcell.core.contact``), and the area and flags (``area_and_flags``). The
pieces that do not depend on the dimension (``start_pass``, ``open_far_pair``, ``subtract_outer``,
``moment_flags``) serve the spatial increment too (``training.fast_step3d``). ``step`` is the
whole planar increment in one call: the features, the perceptron and ``advance``.
Layouts: ``training.fast_cells``; ``out`` (n_free + n_free^2, n) float32 is the perceptron's
output, cells last.
"""

import math

import numba
import numpy as np

from training.fast_cells import coulomb_cap, grain_positions, normal_force, pair_branch
from training.fast_features import features
from training.perceptron import forward_layers


@numba.njit(cache=True, error_model="numpy")
def free_displacement(out, m_in, unbalanced, scaling, law):
    """The free-DOF displacement (n_free, n) [m] the network asks for: the un-normalised rate times
    D norm(d_eps), minus the ramped relaxation C F / kn (C = compliance_scale (I + out's matrix))."""
    n = m_in.shape[0]
    n_free = unbalanced.shape[0]
    rate_mean, rate_std = scaling.rate_mean, scaling.rate_std
    compliance_scale, diameter, kn, ramp = law.compliance_scale, law.diameter, law.kn, law.ramp
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
    return d_free


@numba.njit(cache=True, error_model="numpy")
def release_pair(x_i, x_j, reach, held_i, held_j, square):
    """The rest rule's test of one pair in every cell: where grain i or j is held (held_i, held_j (n,)) and
    the centres x_i, x_j (dim, n) [m] are within ``reach`` [m], both are released (set False). Returns
    whether some cell released one; ``square`` (n,) is scratch. Passes over rows, so that they vectorise,
    and no square root: sqrt(s) <= reach exactly where s <= ``sqrt_bound(reach)``."""
    bound = sqrt_bound(reach)
    if x_i.shape[0] == 3:  # one pass (0.0 + b0^2 + b1^2 + b2^2 in this order, as the passes below)
        i0, i1, i2, j0, j1, j2 = x_i[0], x_i[1], x_i[2], x_j[0], x_j[1], x_j[2]
        for c in range(square.shape[0]):
            b0, b1, b2 = j0[c] - i0[c], j1[c] - i1[c], j2[c] - i2[c]
            square[c] = b0 * b0 + b1 * b1 + b2 * b2
    else:
        square[:] = 0.0
        for a in range(x_i.shape[0]):
            row_i, row_j = x_i[a], x_j[a]
            for c in range(square.shape[0]):
                b = row_j[c] - row_i[c]
                square[c] += b * b
    released = False
    for c in range(square.shape[0]):
        hit = (held_i[c] | held_j[c]) & (square[c] <= bound)
        held_i[c] = held_i[c] & (not hit)
        held_j[c] = held_j[c] & (not hit)
        released |= hit
    return released


@numba.njit(cache=True, error_model="numpy")
def sqrt_bound(reach):
    """The largest float64 s with math.sqrt(s) <= reach (reach >= 0): the correctly rounded square root is
    monotone, so sqrt(s) <= reach exactly where s <= this bound."""
    bound = reach * reach
    while math.sqrt(bound) > reach:
        bound = np.nextafter(bound, 0.0)
    while math.sqrt(np.nextafter(bound, np.inf)) <= reach:
        bound = np.nextafter(bound, np.inf)
    return bound


@numba.njit(cache=True, error_model="numpy")
def hold_at_rest(size, free, d_eps, d_free, old_contact, cells, tol, new_size, new_free, n_held, held_dof):
    """The new cell size and free positions with the rest rule; returns the new grain centres (n_grains, dim, n).

    A free grain with no contact at the start stays where it is unless a neighbour reaches it
    (repeated until no grain is released: a chain of touching grains is pushed in one increment).
    Writes new_size (dim, n), new_free (n_free, n), held_dof (n_free, n) and n_held (n,); dim = 2
    or 3 (planar or spatial cells, ``cells.frac.shape[1]``).
    """
    n = size.shape[1]
    frac, free_dofs, pairs, radius = cells.frac, cells.free_dofs, cells.pairs, cells.radius
    n_free = free_dofs.shape[0]
    n_grains, dim = frac.shape
    touched = np.zeros((n_grains, n), dtype=np.bool_)
    for p in range(pairs.shape[0]):
        contact, touched_i, touched_j = old_contact[p], touched[pairs[p, 0]], touched[pairs[p, 1]]
        for c in range(n):
            touched_i[c] |= contact[c]
            touched_j[c] |= contact[c]
    for k in range(n_free):
        touched_g, new_free_k, free_k, d_free_k = touched[free_dofs[k, 0]], new_free[k], free[k], d_free[k]
        for c in range(n):
            new_free_k[c] = free_k[c] + d_free_k[c] if touched_g[c] else free_k[c]
    probe = d_eps.reshape(n * dim)  # d_eps[c, a] = probe[dim c + a]: a stride the loop vectorises with
    for a in range(dim):
        new_size_a, size_a = new_size[a], size[a]
        for c in range(n):
            new_size_a[c] = size_a[c] * (1.0 - probe[dim * c + a])
    n_untouched = 0
    for k in range(n_free):
        touched_g = touched[free_dofs[k, 0]]
        for c in range(n):
            n_untouched += np.int64(not touched_g[c])
    x = np.empty((n_grains, dim, n))
    if n_untouched == 0:  # every free grain touches: none is held
        held_dof[:] = False
        n_held[:] = 0
    else:
        held = np.zeros((n_grains, n), dtype=np.bool_)
        square = np.empty(n)
        for k in range(n_free):
            held_g, touched_g = held[free_dofs[k, 0]], touched[free_dofs[k, 0]]
            for c in range(n):
                held_g[c] = not touched_g[c]
        for _ in range(n_grains):
            if not held.any():
                break
            grain_positions(new_size, new_free, frac, free_dofs, x)
            released = False
            for p in range(pairs.shape[0]):
                i = pairs[p, 0]
                j = pairs[p, 1]
                released |= release_pair(x[i], x[j], (radius[i] + radius[j]) * (1.0 + tol), held[i], held[j], square)
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
    grain_positions(new_size, new_free, frac, free_dofs, x)
    return x


@numba.njit(cache=True, error_model="numpy")
def start_pass(x, capped_any, opened_any):
    """A contact pass over the grain centres x (n_grains, dim, n) begins: the flags (n,) cleared, the
    moment (dim, dim, n) [N m] zero (returned)."""
    capped_any[:] = False
    opened_any[:] = False
    return np.zeros((x.shape[1], x.shape[1], x.shape[2]))


@numba.njit(cache=True, error_model="numpy")
def open_far_pair(p, old_fn, new_shear, opened_any):
    """Pair p, within reach of no cell: its springs new_shear[p] (n,) or (3, n) [N] are reset, and a
    cell where the pair carried a normal force old_fn[p] (n,) [N] is flagged in opened_any (n,)."""
    springs = new_shear[p].reshape(-1)
    for k in range(springs.shape[0]):  # a loop, not a slice's fill: it vectorises
        springs[k] = 0.0
    old_fn_p = old_fn[p]
    for c in range(old_fn_p.shape[0]):
        opened_any[c] = opened_any[c] | (old_fn_p[c] > 0.0)


@numba.njit(cache=True, error_model="numpy", inline="always")
def subtract_outer(moment, c, force, branch):
    """moment[:, :, c] -= force (x) branch: a pair's force on grain i [N] and its branch x_j - x_i [m],
    tuples of dim floats, into the compression-positive moment (dim, dim, n) [N m] of cell c."""
    for a in range(len(force)):
        for e in range(len(branch)):
            moment[a, e, c] -= force[a] * branch[e]


@numba.njit(cache=True, error_model="numpy")
def subtract_outer_rows(moment, force, branch):
    """moment[a, e] -= force[a] * branch[e] for every cell: one pair's forces on grain i (dim, n) [N] and
    branches x_j - x_i (dim, n) [m] into the compression-positive moment (dim, dim, n) [N m]. A pass of its own
    after the pair's pass over the cells, which then vectorises (the nine writes in it would need too many
    alias checks); each moment entry takes the pairs in the same order, so no bit changes."""
    for a in range(moment.shape[0]):
        for e in range(moment.shape[1]):
            row, force_a, branch_e = moment[a, e], force[a], branch[e]
            for c in range(row.shape[0]):
                row[c] -= force_a[c] * branch_e[c]


@numba.njit(cache=True, error_model="numpy")
def moment_flags(moment, m_in, ramp, mechanism, ramped, moment_out):
    """The mechanism flag (no pair carries force: the moment (dim, dim, n) is zero) and the ramp flag
    (load fraction m_in < ramp) of each cell (n,), and the moment copied cells first into moment_out
    (n, dim, dim); dim 2 or 3. One pass over the cells per component (they vectorise)."""
    dim = moment.shape[0]
    n = moment.shape[2]
    for c in range(n):
        ramped[c] = m_in[c] < ramp
        mechanism[c] = True
    flat = moment_out.reshape((n, dim * dim))
    for a in range(dim):
        for e in range(dim):
            row, column = moment[a, e], a * dim + e
            for c in range(n):
                value = row[c]
                mechanism[c] = mechanism[c] and value == 0.0
                flat[c, column] = value


@numba.njit(cache=True, error_model="numpy")
def contact_pass(x, shear, before, cells, law, new_shear, capped_any, opened_any):
    """The contact law at the new grain centres x: writes new_shear (n_pairs, n) and the flags
    capped_any, opened_any (n,); returns the compression-positive moment (2, 2, n) [N m]."""
    n = x.shape[2]
    pairs, radius = cells.pairs, cells.radius
    kn, kt, mu, tol = law.kn, law.kt, law.mu, law.tol
    old_branch, old_contact, old_fn = before.old_branch, before.old_contact, before.old_fn
    moment = start_pass(x, capped_any, opened_any)
    b0_p, b1_p = np.empty(n), np.empty(n)
    for p in range(pairs.shape[0]):
        _, _, rsum, reach, near = pair_branch(x, pairs, radius, tol, p, b0_p, b1_p)
        if not near:
            open_far_pair(p, old_fn, new_shear, opened_any)
            continue
        for c in range(n):
            b0 = b0_p[c]
            b1 = b1_p[c]
            d = math.sqrt(b0 * b0 + b1 * b1)
            touching = d <= reach
            fn = normal_force(rsum - d, kn) if touching else 0.0
            ob0 = old_branch[p, 0, c]
            ob1 = old_branch[p, 1, c]
            mid0 = 0.5 * (ob0 + b0)
            mid1 = 0.5 * (ob1 + b1)
            inv_norm = 1.0 / math.sqrt(mid0 * mid0 + mid1 * mid1)
            trial = (shear[p, c] if old_contact[p, c] else 0.0) + kt * (
                (b0 - ob0) * -(mid1 * inv_norm) + (b1 - ob1) * (mid0 * inv_norm))
            fs = coulomb_cap(trial, fn, mu) if touching else 0.0
            new_shear[p, c] = fs
            capped_any[c] |= touching and abs(trial) > mu * fn
            opened_any[c] |= old_fn[p, c] > 0.0 and fn == 0.0
            inv_d = 1.0 / d
            u0 = b0 * inv_d
            u1 = b1 * inv_d
            f0 = -fn * u0 + fs * -u1
            f1 = -fn * u1 + fs * u0
            subtract_outer(moment, c, (f0, f1), (b0, b1))
    return moment


@numba.njit(cache=True, error_model="numpy")
def area_and_flags(x, moment, m_in, outer, ramp, area, mechanism, ramped, moment_out):
    """The area (n,) [m^2] of the outer polygon, and as ``moment_flags`` the mechanism and ramp flags (n,) and
    the moment (2, 2, n) copied cells first into moment_out (n, 2, 2) (here with the planar stride written
    out, so that the copy vectorises)."""
    n = x.shape[2]
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
    m00, m01, m10, m11 = moment[0, 0], moment[0, 1], moment[1, 0], moment[1, 1]
    for c in range(n):
        ramped[c] = m_in[c] < ramp
        mechanism[c] = m00[c] == 0.0 and m01[c] == 0.0 and m10[c] == 0.0 and m11[c] == 0.0
    flat = moment_out.reshape(4 * n)
    for c in range(n):
        flat[4 * c] = m00[c]
        flat[4 * c + 1] = m01[c]
        flat[4 * c + 2] = m10[c]
        flat[4 * c + 3] = m11[c]


@numba.njit(cache=True, error_model="numpy")
def advance(size, free, shear, d_eps, out, cells, law, scaling, before, result):
    """Free-DOF displacement from the network output ``out``, then the contact law: fills ``result``
    (``training.fast_tables.Advanced``) from the state before the increment and ``before``."""
    d_free = free_displacement(out, before.m, before.unbalanced, scaling, law)
    x = hold_at_rest(size, free, d_eps, d_free, before.old_contact, cells, law.tol, result.new_size, result.new_free,
                     result.n_held, result.held_dof)
    moment = contact_pass(x, shear, before, cells, law, result.new_shear, result.capped, result.opened)
    area_and_flags(x, moment, before.m, cells.outer, law.ramp, result.area, result.mechanism, result.ramped,
                   result.moment)


@numba.njit(cache=True, error_model="numpy")
def branch_counts(result, counts):
    """The cells (int64) of ``result`` (``training.fast_tables.Advanced``) that are capped, opened, mechanism,
    ramped, and the grains held at rest summed over the cells, written into ``counts`` (5,)."""
    capped, opened, mechanism, ramped, n_held = result.capped, result.opened, result.mechanism, result.ramped, result.n_held
    n_capped = n_opened = n_mechanism = n_ramped = n_grains = 0
    for c in range(n_held.shape[0]):
        n_capped += np.int64(capped[c])
        n_opened += np.int64(opened[c])
        n_mechanism += np.int64(mechanism[c])
        n_ramped += np.int64(ramped[c])
        n_grains += n_held[c]
    counts[0] = n_capped
    counts[1] = n_opened
    counts[2] = n_mechanism
    counts[3] = n_ramped
    counts[4] = n_grains


@numba.njit(cache=True, error_model="numpy")
def step(size, free, shear, d_eps, cells, law, scaling, weights, biases, before, layers, result, counts):
    """One whole planar increment in one call: ``training.fast_features.features`` into ``before``, the
    perceptron (``training.perceptron.forward_layers``: ``weights``, ``biases`` and the layers' outputs
    ``layers``, tuples, input layer first), ``advance`` on its output ``layers[-1]`` into ``result``, and
    ``branch_counts`` into ``counts``; the same operations as these calls apart."""
    features(size, free, shear, d_eps, cells, law, scaling, before)
    forward_layers(weights, biases, before.feats, layers)
    advance(size, free, shear, d_eps, layers[-1], cells, law, scaling, before, result)
    branch_counts(result, counts)
