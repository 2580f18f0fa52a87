"""The consistent tangent of the compiled meso-ANN increment (numba, float64): forward mode.

d(S_nn, S_tt)/d(eps_n, eps_t) of the increment ``training.fast_increment.advance`` took, by
forward-mode differentiation of the features (``probe_feature_tangent``), of the network
(``training.mlp.Perceptron.jvp``, in ``training.inference``) and of the increment
(``moment_tangent``); equal to torch autograd of ``MesoNet.advance`` up to the float32 rounding of
the network. A pair that no cell has within reach is skipped after the square-root-free test
of ``training.fast_cells.pair_branch`` (its contribution is zero in every cell; no bit changes).
Layouts: ``training.fast_cells``.
"""

import math

import numba
import numpy as np

from training.fast_cells import coulomb_cap, grain_positions, normal_force, pair_branch


@numba.njit(cache=True, error_model="numpy")
def probe_feature_tangent(d_eps, m, feature_std, f_dot):
    """Derivative of the two z-scored probe-direction features with respect to d_eps.

    d_eps (n, 2), m = norm(d_eps) (n,); output f_dot (2, 2, n) float32: direction j, feature a (0,
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
def moment_tangent(size, free, shear, d_eps, out, out_dot, cells, law, scaling, before, result, tangent):
    """Consistent tangent d(S_nn, S_tt)/d(eps_n, eps_t) [N m] of the increment ``fast_increment.advance`` took: forward mode.

    Arrays as in ``fast_increment.advance`` (its inputs and its ``result``: new_size, new_free,
    held_dof); ``shear`` (n_pairs, n) is the tangential force before the increment; out_dot (2,
    n_outputs, n) the derivative of the network output along d_eps_n, d_eps_t
    (``training.inference.FastAdvance``). Output tangent (n, 2, 2): [c, i, j] = d S_ii / d eps_j,
    compression positive. Branch choices (contact, Coulomb cap, held grains, relaxation ramp)
    are those of the increment, as autograd takes them; the derivative is zero where
    ``advance`` puts a constant.
    """
    frac, free_dofs, pairs, radius = cells.frac, cells.free_dofs, cells.pairs, cells.radius
    compliance_scale, diameter, kn, kt, mu, tol, ramp = (law.compliance_scale, law.diameter, law.kn, law.kt, law.mu,
                                                         law.tol, law.ramp)
    rate_mean, rate_std = scaling.rate_mean, scaling.rate_std
    m_in, unbalanced, old_branch, old_contact = before.m, before.unbalanced, before.old_branch, before.old_contact
    new_size, new_free, held_dof = result.new_size, result.new_free, result.held_dof
    n = size.shape[1]
    n_free = free_dofs.shape[0]
    n_grains = frac.shape[0]
    x = np.empty((n_grains, 2, n))
    grain_positions(new_size, new_free, frac, free_dofs, x)
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
    b0_p, b1_p = np.empty(n), np.empty(n)
    for p in range(pairs.shape[0]):
        i_g, j_g, rsum, reach, near = pair_branch(x, pairs, radius, tol, p, b0_p, b1_p)
        if not near:
            continue
        for c in range(n):
            b0 = b0_p[c]
            b1 = b1_p[c]
            d = math.sqrt(b0 * b0 + b1 * b1)
            if d > reach:
                continue
            fn = normal_force(rsum - d, kn)
            ob0, ob1 = old_branch[p, 0, c], old_branch[p, 1, c]
            mid0, mid1 = 0.5 * (ob0 + b0), 0.5 * (ob1 + b1)
            norm = math.sqrt(mid0 * mid0 + mid1 * mid1)
            n0, n1 = mid0 / norm, mid1 / norm
            rel0, rel1 = b0 - ob0, b1 - ob1
            trial = (shear[p, c] if old_contact[p, c] else 0.0) + kt * (rel0 * -n1 + rel1 * n0)
            fs = coulomb_cap(trial, fn, mu)
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
