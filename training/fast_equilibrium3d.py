"""Exact equilibrium corrections of the meso-ANN's step of spatial cells, compiled (numba, float64).

The network's free-DOF displacement is a first guess (the DEM's rest rule applied by ``hold_guess3d``);
``newton3d`` then takes up to a fixed number of Newton steps on the balance of the free DOFs, with
the residual and its Jacobian from the exact spatial contact law of the increment
(``training.fast_step3d.contact_pass3``; the derivatives are written above ``pair_force_jacobian``):

    R(d) = net contact force on every free DOF  [N],  J = dR/dd  [N/m]  (n_free x n_free).

A Newton step solves (K + lambda I) delta = R per cell, K = -J + REGULARISATION kn I (Gaussian
elimination with partial pivoting): the small diagonal term leaves a free DOF that no contact
touches where it is and bounds the step along a mechanism. Two rules globalise the steps, each
counted per cell:

- shift: where Newton's step (lambda = 0) does no positive work along the unbalanced force,
  R . delta <= 0 (the grains near an unstable equilibrium, which the DEM's damped dynamics move
  away from), lambda = SHIFT kn, doubled until R . delta > 0, and the shifted step is taken in full;
- line search: an unshifted step taken is alpha delta for the first alpha of 1, 1/2, ...,
  2^-HALVINGS whose sum of squared residuals is below the current one, else 2^-HALVINGS delta.

Without either (shift 0, halvings 0) the steps are the full Newton steps, bit for bit. A cell is
corrected only while its force ratio, max abs(R) over its largest normal force (the DEM's
criterion, ``DemSettings.force_tolerance``), exceeds ``tolerance``, and only when its probe is at
least ``Physics.ramp`` (a zero increment stays a no-op).

Layouts: ``training.fast_cells`` (cells last, one cell a vector lane; a cell's result does not
depend on its batch). Sign convention: compression positive.
"""

import math

import numba
import numpy as np

from training.fast_cells import grain_positions, normal_force
from training.fast_increment import hold_at_rest
from training.fast_step3d import pair_branch3, pair_force3
from warp_hcell.core.contact import CAP_SLACK

REGULARISATION = 1e-9
"""Diagonal stiffness added to -J in every Newton step, as a fraction of kn [-]."""

HALVINGS = 5
"""The most halvings of a Newton step whose full length does not lower the sum of squared residuals [-]."""

SHIFT = 1e-3
"""First diagonal stiffness added to the Newton matrix of a cell whose Newton step does no positive work
along its unbalanced force, doubled until it does, as a fraction of kn [-]."""


@numba.njit(cache=True, error_model="numpy", inline="always")
def _mat3(a, b, out):
    """out (3, 3) = a @ b for (3, 3) arrays, a fixed order of operations (no BLAS)."""
    for r_ in range(3):
        for e in range(3):
            out[r_, e] = a[r_, 0] * b[0, e] + a[r_, 1] * b[1, e] + a[r_, 2] * b[2, e]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _scaled_projector(scale, h, out):
    """out = scale (I - h h^T) (3, 3): the derivative of scale times the unit direction h (3,) of a vector,
    per unit of that vector's change (the rescaled spring, the capped force)."""
    for a in range(3):
        for e in range(3):
            out[a, e] = scale * ((1.0 if a == e else 0.0) - h[a] * h[e])


# Jacobian of the force g on grain i of a touching pair, branch b = x_j - x_i (d = norm(b),
# u = b / d, P = I - u u^T; overlap > 0 for the normal terms; a^ = a / norm(a)):
#   normal:          d(-f_n u)/db = kn u u^T - (f_n / d) P
#   carried spring:  s_c = norm(s) q / norm(q), q = s - (s.u) u,
#                    ds_c/db = (norm(s) / norm(q)) (I - q^ q^^T) (-(u s^T + (s.u) I) P / d)
#   slip:            r - (r.m) m, r = b - b_old, m the unit mid-increment branch,
#                    dm/db = (I - m m^T) / norm(b_old + b),
#                    d(slip)/db = I - m m^T - (m r^T + (r.m) I) dm/db
#   Coulomb cap:     where norm(t) > mu f_n (1 + CAP_SLACK), t = s_c + kt slip:
#                    f = mu f_n t^,  df/db = (mu f_n / norm(t)) (I - t^ t^^T) dt/db - mu kn t^ u^T
@numba.njit(cache=True, error_model="numpy", inline="always")
def pair_force_jacobian(b, ob, s, was_contact, rsum, reach, kn, kt, mu, slack, g, dg, work):
    """Force g (3,) [N] on grain i of one pair of one cell by the spatial contact law and dg = dg/db (3, 3)
    [N/m] (module docstring); b, ob: the new and old branch x_j - x_i (3,) [m]; s: the old spring (3,) [N],
    kept where ``was_contact``; work: scratch (8, 3, 3). Returns whether the pair touches (g and dg are
    zero otherwise)."""
    d = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    if not d <= reach:
        g[0], g[1], g[2] = 0.0, 0.0, 0.0
        dg[:, :] = 0.0
        return False
    overlap = rsum - d
    fn = normal_force(overlap, kn)
    u0, u1, u2 = b[0] / d, b[1] / d, b[2] / d
    du, dm, dsc, dslip, tmp, df, dq, dt = work[0], work[1], work[2], work[3], work[4], work[5], work[6], work[7]
    u = (u0, u1, u2)
    normal_slope = kn if overlap > 0.0 else 0.0
    mid0, mid1, mid2 = 0.5 * (ob[0] + b[0]), 0.5 * (ob[1] + b[1]), 0.5 * (ob[2] + b[2])
    mid_norm = math.sqrt(mid0 * mid0 + mid1 * mid1 + mid2 * mid2)
    m = (mid0 / mid_norm, mid1 / mid_norm, mid2 / mid_norm)
    for a in range(3):
        for e in range(3):
            eye = 1.0 if a == e else 0.0
            du[a, e] = (eye - u[a] * u[e]) / d
            dm[a, e] = (eye - m[a] * m[e]) * (0.5 / mid_norm)
    sc0, sc1, sc2 = 0.0, 0.0, 0.0
    dsc[:, :] = 0.0
    if was_contact:
        along = s[0] * u0 + s[1] * u1 + s[2] * u2
        q0, q1, q2 = s[0] - along * u0, s[1] - along * u1, s[2] - along * u2
        before2 = s[0] * s[0] + s[1] * s[1] + s[2] * s[2]
        after2 = q0 * q0 + q1 * q1 + q2 * q2
        for a in range(3):
            for e in range(3):
                tmp[a, e] = -(u[a] * s[e] + (along if a == e else 0.0))
        _mat3(tmp, du, dq)
        dsc[:, :] = dq
        if after2 > 0:
            ratio = math.sqrt(before2 / after2)
            qn = math.sqrt(after2)
            qh = (q0 / qn, q1 / qn, q2 / qn)
            sc0, sc1, sc2 = q0 * ratio, q1 * ratio, q2 * ratio
            _scaled_projector(ratio, qh, tmp)
            _mat3(tmp, dq, dsc)
        else:
            sc0, sc1, sc2 = q0, q1, q2
    r0, r1, r2 = b[0] - ob[0], b[1] - ob[1], b[2] - ob[2]
    r = (r0, r1, r2)
    along_r = r0 * m[0] + r1 * m[1] + r2 * m[2]
    for e in range(3):
        dalong_e = m[e] + r[0] * dm[0, e] + r[1] * dm[1, e] + r[2] * dm[2, e]
        for a in range(3):
            dslip[a, e] = (1.0 if a == e else 0.0) - m[a] * dalong_e - along_r * dm[a, e]
    t0 = sc0 + kt * (r0 - along_r * m[0])
    t1 = sc1 + kt * (r1 - along_r * m[1])
    t2 = sc2 + kt * (r2 - along_r * m[2])
    for a in range(3):
        for e in range(3):
            dt[a, e] = dsc[a, e] + kt * dslip[a, e]
            df[a, e] = dt[a, e]
    trial = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    cap = mu * fn
    f0, f1, f2 = t0, t1, t2
    if trial > cap * slack:
        scale = cap / (trial if trial > 0 else 1.0)
        th = (t0 / trial, t1 / trial, t2 / trial)
        f0, f1, f2 = t0 * scale, t1 * scale, t2 * scale
        _scaled_projector(scale, th, tmp)
        _mat3(tmp, dt, df)
        for a in range(3):
            for e in range(3):
                df[a, e] -= mu * normal_slope * th[a] * u[e]
    g[0], g[1], g[2] = -fn * u0 + f0, -fn * u1 + f1, -fn * u2 + f2
    for a in range(3):
        for e in range(3):
            dg[a, e] = normal_slope * u[a] * u[e] - fn * du[a, e] + df[a, e]
    return True


@numba.njit(cache=True, error_model="numpy")
def residual3(x, shear, old_branch, old_contact, cells, law, residual, fn_max):
    """Net contact force on the free DOFs ``residual`` (n_free, n) [N] and the largest normal force ``fn_max``
    (n,) [N] of every cell at the grain centres x (n_grains, 3, n) after the increment, by the operations of
    ``training.fast_step3d.contact_pass3`` (cells innermost); shear (n_pairs, 3, n), old_branch, old_contact:
    the state before the increment."""
    n = x.shape[2]
    pairs, radius, free_slot = cells.pairs, cells.radius, cells.free_slot
    kn, kt, mu, tol = law.kn, law.kt, law.mu, law.tol
    slack = 1.0 + CAP_SLACK
    residual[:, :] = 0.0
    fn_max[:] = 0.0
    b = np.empty((3, n))
    g = np.empty((3, n))
    for p in range(pairs.shape[0]):
        i, j, rsum, reach, near = pair_branch3(x, pairs, radius, tol, p, b[0], b[1], b[2])
        if not near:
            continue
        for c in range(n):
            touching, fn, u0, u1, u2, f0, f1, f2, trial, cap = pair_force3(
                b[0, c], b[1, c], b[2, c], old_branch[p, 0, c], old_branch[p, 1, c], old_branch[p, 2, c],
                old_contact[p, c], shear[p, 0, c], shear[p, 1, c], shear[p, 2, c], rsum, reach, kn, kt, mu, slack)
            fn_max[c] = max(fn_max[c], fn)
            g[0, c] = -fn * u0 + f0
            g[1, c] = -fn * u1 + f1
            g[2, c] = -fn * u2 + f2
        for a in range(3):
            g_a = g[a]
            k = free_slot[i, a]
            if k >= 0:
                net_k = residual[k]
                for c in range(n):
                    net_k[c] += g_a[c]
            k = free_slot[j, a]
            if k >= 0:
                net_k = residual[k]
                for c in range(n):
                    net_k[c] -= g_a[c]


@numba.njit(cache=True, error_model="numpy")
def residual_jacobian3(x, shear, old_branch, old_contact, cells, law, active, residual, jacobian, fn_max):
    """Net contact force on the free DOFs ``residual`` (n_free, n) [N], its Jacobian ``jacobian`` (n, n_free,
    n_free) [N/m] (cells first: one cell's matrix contiguous) with respect to the free coordinates and the largest normal force ``fn_max`` (n,) [N]
    of the cells flagged ``active`` (n,) bool (the others are left at zero), at the grain centres x
    (n_grains, 3, n) after the increment; shear (n_pairs, 3, n) and old_branch, old_contact: the state
    before it."""
    n = x.shape[2]
    pairs, radius, free_slot = cells.pairs, cells.radius, cells.free_slot
    kn, kt, mu, tol = law.kn, law.kt, law.mu, law.tol
    slack = 1.0 + CAP_SLACK
    residual[:, :] = 0.0
    jacobian[:, :, :] = 0.0
    fn_max[:] = 0.0
    bb = np.empty((3, n))
    b, ob, s, g, dg = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty((3, 3))
    work = np.empty((8, 3, 3))
    slots = np.empty(6, dtype=np.int64)
    signs = np.empty(6)
    for p in range(pairs.shape[0]):
        i, j, rsum, reach, near = pair_branch3(x, pairs, radius, tol, p, bb[0], bb[1], bb[2])
        if not near:
            continue
        for a in range(3):
            slots[a], signs[a] = free_slot[i, a], 1.0
            slots[3 + a], signs[3 + a] = free_slot[j, a], -1.0
        bound = (reach * (1.0 + 1e-9)) ** 2
        for c in range(n):
            if not active[c] or bb[0, c] * bb[0, c] + bb[1, c] * bb[1, c] + bb[2, c] * bb[2, c] > bound:
                continue  # out of reach (the margin covers the rounding of the square-root-free test)
            for a in range(3):
                b[a] = bb[a, c]
                ob[a] = old_branch[p, a, c]
                s[a] = shear[p, a, c]
            if not pair_force_jacobian(b, ob, s, old_contact[p, c], rsum, reach, kn, kt, mu, slack, g, dg, work):
                continue
            fn_max[c] = max(fn_max[c], normal_force(rsum - math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]), kn))
            for r_ in range(6):
                k = slots[r_]
                if k < 0:
                    continue
                residual[k, c] += signs[r_] * g[r_ % 3]
                for q_ in range(6):
                    col = slots[q_]
                    if col >= 0:
                        # g acts on i (+) and j (-); b = x_j - x_i, so db/dx_j = I, db/dx_i = -I
                        jacobian[c, k, col] += signs[r_] * (-signs[q_]) * dg[r_ % 3, q_ % 3]


@numba.njit(cache=True, error_model="numpy")
def solve_small(a, rhs, out):
    """out (m,) = a^-1 rhs for a (m, m) (overwritten) by Gaussian elimination with partial pivoting;
    returns False (out zero) for a singular a."""
    m = rhs.shape[0]
    v = rhs.copy()
    for col in range(m):
        pivot = col
        for r_ in range(col + 1, m):
            if abs(a[r_, col]) > abs(a[pivot, col]):
                pivot = r_
        if a[pivot, col] == 0.0:
            out[:] = 0.0
            return False
        if pivot != col:
            for e in range(m):
                a[col, e], a[pivot, e] = a[pivot, e], a[col, e]
            v[col], v[pivot] = v[pivot], v[col]
        for r_ in range(col + 1, m):
            factor = a[r_, col] / a[col, col]
            if factor != 0.0:
                for e in range(col, m):
                    a[r_, e] -= factor * a[col, e]
                v[r_] -= factor * v[col]
    for r_ in range(m - 1, -1, -1):
        total = v[r_]
        for e in range(r_ + 1, m):
            total -= a[r_, e] * out[e]
        out[r_] = total / a[r_, r_]
    return True


@numba.njit(cache=True, error_model="numpy", inline="always")
def _work(force, step):
    """The work of the unbalanced force (m,) [N] along the step (m,) [m] (J), a fixed order of summation."""
    total = 0.0
    for k in range(force.shape[0]):
        total += force[k] * step[k]
    return total


@numba.njit(cache=True, error_model="numpy")
def _newton_direction(jacobian, residual, c, kn, shift, a_c, a_w, rhs, delta):
    """Newton step ``delta`` (n_free,) [m] of cell c from its residual (n_free, n) [N] and Jacobian
    (n, n_free, n_free) [N/m], its matrix shifted by shift kn, doubled, until the step does positive
    work along the residual (module docstring); ``a_c``, ``a_w``, ``rhs``: work arrays. Returns the
    sum of squared residuals [N^2] and whether the matrix was shifted."""
    n_free = rhs.shape[0]
    total = 0.0
    for k in range(n_free):
        rhs[k] = residual[k, c]
        total += residual[k, c] * residual[k, c]
        for e in range(n_free):
            a_c[k, e] = -jacobian[c, k, e]
        a_c[k, k] += REGULARISATION * kn
    for k in range(n_free):
        for e in range(n_free):
            a_w[k, e] = a_c[k, e]
    solve_small(a_w, rhs, delta)
    was_shifted = False
    lam = shift * kn
    for _ in range(64):
        if not shift > 0.0 or _work(rhs, delta) > 0.0:
            break
        was_shifted = True
        for k in range(n_free):
            for e in range(n_free):
                a_w[k, e] = a_c[k, e]
            a_w[k, k] += lam
        solve_small(a_w, rhs, delta)
        lam *= 2.0
    return total, was_shifted


@numba.njit(cache=True, error_model="numpy")
def _line_search(free, d_free, step_d, alpha, pending, full, merit, halvings, new_size, position, x, shear, before,
                 cells, law, trial_residual, trial_fn_max, residual, fn_max, shortened):
    """Take alpha step_d for the pending cells (n,): the first alpha of 1, 1/2, ..., 2^-halvings whose sum of
    squared residuals is below ``merit`` (n,) [N^2], else the last; a shifted step (``full``) in full. Updates
    d_free, residual, fn_max and shortened (steps taken at alpha < 1) in place."""
    n_free, n = d_free.shape
    frac, free_dofs = cells.frac, cells.free_dofs
    for trial in range(halvings + 1):
        for k in range(n_free):
            for c in range(n):
                moved = d_free[k, c] + alpha[c] * step_d[k, c] if pending[c] else d_free[k, c]
                position[k, c] = free[k, c] + moved
        grain_positions(new_size, position, frac, free_dofs, x)
        residual3(x, shear, before.old_branch, before.old_contact, cells, law, trial_residual, trial_fn_max)
        for c in range(n):
            if not pending[c]:
                continue
            total = 0.0
            for k in range(n_free):
                total += trial_residual[k, c] * trial_residual[k, c]
            if total < merit[c] or trial == halvings or full[c]:
                pending[c] = False
                for k in range(n_free):
                    d_free[k, c] += alpha[c] * step_d[k, c]
                    residual[k, c] = trial_residual[k, c]
                fn_max[c] = trial_fn_max[c]
                if trial > 0:
                    shortened[c] += 1
            else:
                alpha[c] *= 0.5
        if not pending.any():
            break


@numba.njit(cache=True, error_model="numpy")
def hold_guess3d(size, free, d_eps, d_free, cells, law, before):
    """The DEM's rest rule (``fast_increment.hold_at_rest``) on the first guess ``d_free`` (n_free, n) [m], in
    place: the free DOFs of the grains it holds get zero displacement (arguments: ``newton3d``)."""
    n = size.shape[1]
    n_free = cells.free_dofs.shape[0]
    held_dof = np.empty((n_free, n), dtype=np.bool_)
    hold_at_rest(size, free, d_eps, d_free, before.old_contact, cells, law.tol, np.empty((3, n)),
                 np.empty((n_free, n)), np.empty(n, dtype=np.int64), held_dof)
    for k in range(n_free):
        for c in range(n):
            if held_dof[k, c]:
                d_free[k, c] = 0.0


@numba.njit(cache=True, error_model="numpy")
def newton3d(size, free, shear, d_eps, d_free, cells, law, before, iterations, tolerance, halvings, shift, ratios,
             corrections, shortened, shifted):
    """Newton corrections of the free-DOF displacement ``d_free`` (n_free, n) [m], in place. Each cell is a lane: one stopped at ``iterations`` steps continues bit for
    bit in another call from its ``d_free``, alone or in any batch.

    Args:
        size (3, n), free (n_free, n), shear (n_pairs, 3, n), d_eps (n, 3): the state and probe;
        before: ``training.fast_tables.Before`` of the state (``fast_step3d.features3d``);
        iterations: the most Newton steps per cell (>= 0); tolerance: force ratio [-] below which
            a cell is not corrected; halvings: the most halvings of a step (0: full steps);
            shift: a climbing step's first matrix shift, a fraction of kn (0: never).

    Writes ratios (2, n): the force ratio at the first guess and after the last step (0: not
    evaluated); corrections, shortened, shifted (n,) int64: Newton steps taken, of them those at
    alpha < 1 and those with a shifted matrix."""
    n = size.shape[1]
    frac, free_dofs = cells.frac, cells.free_dofs
    n_free = free_dofs.shape[0]
    kn = law.kn
    new_size = np.empty((3, n))
    for a in range(3):
        for c in range(n):
            new_size[a, c] = size[a, c] * (1.0 - d_eps[c, a])
    position = np.empty((n_free, n))
    x = np.empty((frac.shape[0], 3, n))
    residual = np.empty((n_free, n))
    jacobian = np.empty((n, n_free, n_free))
    fn_max = np.empty(n)
    trial_residual = np.empty((n_free, n))
    trial_fn_max = np.empty(n)
    step_d = np.empty((n_free, n))
    merit = np.empty(n)
    alpha = np.empty(n)
    active = np.empty(n, dtype=np.bool_)
    for c in range(n):
        active[c] = before.m[c] >= law.ramp
        corrections[c] = 0
        shortened[c] = 0
        shifted[c] = 0
    a_c, rhs, delta = np.empty((n_free, n_free)), np.empty(n_free), np.empty(n_free)
    a_w = np.empty((n_free, n_free))
    full = np.zeros(n, dtype=np.bool_)
    stepping = np.zeros(n, dtype=np.bool_)
    pending = np.zeros(n, dtype=np.bool_)
    for k in range(n_free):
        for c in range(n):
            position[k, c] = free[k, c] + d_free[k, c]
    grain_positions(new_size, position, frac, free_dofs, x)
    residual3(x, shear, before.old_branch, before.old_contact, cells, law, residual, fn_max)
    for step in range(iterations + 1):
        for c in range(n):
            stepping[c] = False
            if not active[c]:
                if step == 0:
                    ratios[0, c] = 0.0
                    ratios[1, c] = 0.0
                continue
            largest = 0.0
            for k in range(n_free):
                largest = max(largest, abs(residual[k, c]))
            ratio = largest / fn_max[c] if fn_max[c] > 0.0 else 0.0
            if step == 0:
                ratios[0, c] = ratio
            ratios[1, c] = ratio
            stepping[c] = ratio > tolerance and step < iterations
        if not stepping.any():
            break
        residual_jacobian3(x, shear, before.old_branch, before.old_contact, cells, law, stepping, residual, jacobian,
                           fn_max)
        for c in range(n):
            active[c] = stepping[c]
            pending[c] = stepping[c]
            alpha[c] = 1.0
            if not stepping[c]:
                continue
            merit[c], full[c] = _newton_direction(jacobian, residual, c, kn, shift, a_c, a_w, rhs, delta)
            if full[c]:
                shifted[c] += 1
            for k in range(n_free):
                step_d[k, c] = delta[k]
            corrections[c] += 1
        _line_search(free, d_free, step_d, alpha, pending, full, merit, halvings, new_size, position, x, shear,
                     before, cells, law, trial_residual, trial_fn_max, residual, fn_max, shortened)


@numba.njit(cache=True, error_model="numpy")
def balance_tangent3d(size, shear, new_size, new_free, held_dof, cells, law, before, tangent):
    """Consistent tangent d(S_nn, S_t1t1, S_t2t2)/d(eps_n, eps_t1, eps_t2) [N m] of a corrected increment, at its end.

    The free DOFs follow the balance R(d, eps) = 0 (``residual3``): dd/deps = K^-1 dR/deps with
    K = -J + REGULARISATION kn I (the Newton matrix of ``newton3d``, the derivative of the equilibrium that
    ``training.equilibrium.corrected_advance`` gives autograd), zero for DOFs the rest rule held; the moment's
    derivative is then taken along (eps, d) through the contact law (``pair_force_jacobian``). Branch choices
    are those of the end state. size (3, n): before the increment; new_size (3, n), new_free (n_free, n),
    held_dof (n_free, n) bool: after it (``training.fast_tables.Advanced``); shear, before: the state and
    ``training.fast_tables.Before`` before it. Output tangent (n, 3, 3): [c, i, j] = d S_ii / d eps_j,
    compression positive."""
    n = size.shape[1]
    frac, free_dofs, free_slot, pairs, radius = cells.frac, cells.free_dofs, cells.free_slot, cells.pairs, cells.radius
    kn, kt, mu, tol = law.kn, law.kt, law.mu, law.tol
    slack = 1.0 + CAP_SLACK
    n_free, n_pairs, n_grains = free_dofs.shape[0], pairs.shape[0], frac.shape[0]
    x = np.empty((n_grains, 3, n))
    grain_positions(new_size, new_free, frac, free_dofs, x)
    b, ob, s = np.empty(3), np.empty(3), np.empty(3)
    g, dg = np.empty((n_pairs, 3)), np.empty((n_pairs, 3, 3))
    branch, bdot = np.empty((n_pairs, 3)), np.empty((n_pairs, 3))
    touching = np.empty(n_pairs, dtype=np.bool_)
    work = np.empty((8, 3, 3))
    k_mat, a_w = np.empty((n_free, n_free)), np.empty((n_free, n_free))
    r_eps, v = np.empty((n_free, 3)), np.empty((3, n_free))
    rhs, sol = np.empty(n_free), np.empty(n_free)
    db = np.empty(3)
    for c in range(n):
        k_mat[:, :] = 0.0
        r_eps[:, :] = 0.0
        for p in range(n_pairs):
            i, j = pairs[p, 0], pairs[p, 1]
            rsum = radius[i] + radius[j]
            for a in range(3):
                b[a] = x[j, a, c] - x[i, a, c]
                ob[a] = before.old_branch[p, a, c]
                s[a] = shear[p, a, c]
                branch[p, a] = b[a]
                # d x / d eps_a of a driven coordinate: -frac size_a (x = frac size_a (1 - eps_a)); free: 0
                dxj = 0.0 if free_slot[j, a] >= 0 else -frac[j, a] * size[a, c]
                dxi = 0.0 if free_slot[i, a] >= 0 else -frac[i, a] * size[a, c]
                bdot[p, a] = dxj - dxi
            touching[p] = pair_force_jacobian(b, ob, s, before.old_contact[p, c], rsum, rsum * (1.0 + tol), kn, kt,
                                              mu, slack, g[p], dg[p], work)
            if not touching[p]:
                continue
            for r_ in range(6):
                k = free_slot[i, r_] if r_ < 3 else free_slot[j, r_ - 3]
                if k < 0:
                    continue
                sign = 1.0 if r_ < 3 else -1.0
                for e in range(3):
                    r_eps[k, e] += sign * dg[p, r_ % 3, e] * bdot[p, e]
                for q_ in range(6):
                    col = free_slot[i, q_] if q_ < 3 else free_slot[j, q_ - 3]
                    if col >= 0:
                        k_mat[k, col] -= sign * (-1.0 if q_ < 3 else 1.0) * dg[p, r_ % 3, q_ % 3]
        for k in range(n_free):
            k_mat[k, k] += REGULARISATION * kn
        for e in range(3):
            for k in range(n_free):
                rhs[k] = r_eps[k, e]
                for q in range(n_free):
                    a_w[k, q] = k_mat[k, q]
            solve_small(a_w, rhs, sol)
            for k in range(n_free):
                v[e, k] = 0.0 if held_dof[k, c] else sol[k]
        for a in range(3):
            for e in range(3):
                tangent[c, a, e] = 0.0
        for p in range(n_pairs):
            if not touching[p]:
                continue
            i, j = pairs[p, 0], pairs[p, 1]
            for e in range(3):
                for a in range(3):
                    db[a] = bdot[p, a] if a == e else 0.0
                    kj, ki = free_slot[j, a], free_slot[i, a]
                    if kj >= 0:
                        db[a] += v[e, kj]
                    if ki >= 0:
                        db[a] -= v[e, ki]
                for a in range(3):
                    dg_a = dg[p, a, 0] * db[0] + dg[p, a, 1] * db[1] + dg[p, a, 2] * db[2]
                    tangent[c, a, e] -= dg_a * branch[p, a] + g[p, a] * db[a]
