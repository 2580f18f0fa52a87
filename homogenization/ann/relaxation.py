"""The DEM's relaxation from rest of the grains a neighbour pushed, the other grains following the balance.

A free grain that nothing presses at the start of an increment starts the hybrid's corrections at rest
(``homogenization.ann.escalation.RELEASE_RULE``). Where a neighbour pushes it lightly, the balance moves it only
as far as the push needs, along the contact normal: at a force ratio below R a contact's tangential force,
capped at mu f_n, is nothing. The DEM, relaxing from rest, pushes it with a finite contact force while the
driving lasts, and the friction of that contact also drags it along the neighbour's tangential motion.

``relax`` runs that relaxation for the pushed grains and the grains within reach of them before or after the
increment (their pushers, which the DEM also starts at rest): their free DOFs start at rest and move by the DEM's
leapfrog with Cundall local damping (``warp_hcell.dem.stepping.damped_velocity``) under the DEM's spatial
contact law of each substep (the spring carried into the tangent plane, grown by kt times the substep's
tangential relative displacement, capped at mu f_n; ``warp_hcell.dem.laws.linear.spatial_contact``), while
every other DOF moves along the straight line from its position before the increment to the one the
balance gave it, in ``n_drive`` substeps; the substeps then continue until the net force on every moving
free DOF is at most ``ratio`` times the cell's largest normal force, or ``max_substeps``. A grain whose net
force is exactly zero is held at rest (the DEM's rule). Masses and time step are the DEM's (density
4/3 pi r^3, dt_factor sqrt(m_min / kn)). Only the pushed grains' end positions are the rule's; the
others keep the balance's (``homogenization.ann.escalation.DemEscalation.relaxed``).

Layout: cells first; one cell per iteration of a compiled loop, so a cell's result does not depend on its batch.
float64. Sign convention: the DEM's (force on grain i of pair (i, j): f_s - f_n u, u = (x_j - x_i) / d).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from training.fast_cells import carried_spring3


@numba.njit(cache=True, error_model="numpy", inline="always")
def _movers(c, x0, x1, simulated, pairs, radius, tol, free_mask, pushed, moving, involved, dynamic, relevant, grains):
    """Cell c: the free DOFs that move (``dynamic`` (n_grains, 3) bool: the pushed ones and the free DOFs of the
    grains within reach of a pushed grain at x0 or x1), the pairs that touch a moving grain (``relevant``), the
    grains of those pairs (``involved`` (n_grains,) bool, and their indices ``grains``), written in place with the
    scratch ``pushed`` and ``moving`` (n_grains,) bool. Returns (number of relevant pairs, number of grains)."""
    n_grains, n_pairs = x0.shape[1], pairs.shape[0]
    for g in range(n_grains):
        pushed[g] = simulated[c, g, 0] or simulated[c, g, 1] or simulated[c, g, 2]
        moving[g] = pushed[g]
    for p in range(n_pairs):
        i, j = pairs[p, 0], pairs[p, 1]
        if pushed[i] == pushed[j]:
            continue
        reach2 = ((radius[i] + radius[j]) * (1.0 + tol)) ** 2
        for xs in (x0, x1):
            b0, b1, b2 = xs[c, j, 0] - xs[c, i, 0], xs[c, j, 1] - xs[c, i, 1], xs[c, j, 2] - xs[c, i, 2]
            if b0 * b0 + b1 * b1 + b2 * b2 <= reach2:
                moving[i] = True
                moving[j] = True
    for g in range(n_grains):
        for a in range(3):
            dynamic[g, a] = simulated[c, g, a] or (moving[g] and free_mask[g, a])
    for g in range(n_grains):
        involved[g] = False
    n_relevant = 0
    for p in range(n_pairs):
        if moving[pairs[p, 0]] or moving[pairs[p, 1]]:
            relevant[n_relevant] = p
            n_relevant += 1
            involved[pairs[p, 0]] = True
            involved[pairs[p, 1]] = True
    n_involved = 0
    for g in range(n_grains):
        if involved[g]:
            grains[n_involved] = g
            n_involved += 1
    return n_relevant, n_involved


@numba.njit(cache=True, error_model="numpy")
def relax(x0, x1, simulated, shear, pairs, radius, inv_mass, dt, kn, kt, mu, tol, damping, n_drive, fn_max, ratio,
          max_substeps, free_mask, x_out, substeps_out):
    """The relaxation of the module docstring, cells first.

    x0 and x1 are the grain centres (n, n_grains, 3) [m] before the increment and after the balance; ``simulated``
    (n, n_grains, 3) bool flags the pushed grains' free DOFs: these and the free DOFs (``free_mask`` (n_grains, 3)
    bool) of the grains within reach of them at x0 or x1 move, the others follow x0 to x1. ``shear``: the pairs'
    springs before the increment (n, n_pairs, 3) [N]; ``pairs`` (n_pairs, 2) int64; ``radius`` (n_grains,) [m];
    ``inv_mass`` (n_grains,) [1/kg]; ``dt`` [s]; ``kn`` and ``kt`` [N/m]; ``mu``, ``tol`` (contact tolerance) and
    ``damping`` [-]; ``n_drive`` (n,) int64, the driving substeps; ``fn_max`` (n,) [N], the cell's largest normal
    force; ``ratio`` [-] and ``max_substeps``: where the substeps stop. Writes ``x_out`` (n, n_grains, 3) [m], the
    centres after the relaxation, and ``substeps_out`` (n,) int64 (max_substeps where the ratio stayed above)."""
    n, n_grains, _ = x0.shape
    n_pairs = pairs.shape[0]
    x = np.empty((n_grains, 3))
    v = np.zeros((n_grains, 3))
    dx = np.empty((n_grains, 3))
    f = np.empty((n_grains, 3))
    spring = np.empty((n_pairs, 3))
    relevant = np.empty(n_pairs, dtype=np.int64)
    dynamic = np.empty((n_grains, 3), dtype=np.bool_)
    pushed = np.empty(n_grains, dtype=np.bool_)
    moving = np.empty(n_grains, dtype=np.bool_)
    involved = np.empty(n_grains, dtype=np.bool_)
    grains = np.empty(n_grains, dtype=np.int64)
    for c in range(n):
        n_relevant, n_involved = _movers(c, x0, x1, simulated, pairs, radius, tol, free_mask, pushed, moving, involved,
                                         dynamic, relevant, grains)
        for g in range(n_grains):
            for a in range(3):
                x[g, a] = x0[c, g, a]
                v[g, a] = 0.0
                dx[g, a] = 0.0
        for p in range(n_pairs):
            for a in range(3):
                spring[p, a] = shear[c, p, a]
        n_phase = max(n_drive[c], 1)
        s, k_phase, ds = 0.0, 0, 1.0 / n_phase
        limit = ratio * fn_max[c]
        k = 0
        while True:
            for h in range(n_involved):
                g = grains[h]
                f[g, 0], f[g, 1], f[g, 2] = 0.0, 0.0, 0.0
            for q in range(n_relevant):  # the DEM's contact law of one substep
                p = relevant[q]
                i, j = pairs[p, 0], pairs[p, 1]
                b0, b1, b2 = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
                rsum = radius[i] + radius[j]
                reach = rsum * (1.0 + tol)
                dist2 = b0 * b0 + b1 * b1 + b2 * b2
                if not dist2 <= reach * reach:
                    spring[p, 0], spring[p, 1], spring[p, 2] = 0.0, 0.0, 0.0
                    continue
                dist = math.sqrt(dist2)
                u0, u1, u2 = b0 / dist, b1 / dist, b2 / dist
                q0, q1, q2 = carried_spring3(spring[p, 0], spring[p, 1], spring[p, 2], u0, u1, u2)
                r0, r1, r2 = dx[j, 0] - dx[i, 0], dx[j, 1] - dx[i, 1], dx[j, 2] - dx[i, 2]
                rn = r0 * u0 + r1 * u1 + r2 * u2
                t0, t1, t2 = q0 + kt * (r0 - rn * u0), q1 + kt * (r1 - rn * u1), q2 + kt * (r2 - rn * u2)
                fn = kn * max(rsum - dist, 0.0)
                cap = mu * fn
                size = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
                if size > cap:
                    scale = cap / size if size > 0.0 else 0.0
                    t0, t1, t2 = t0 * scale, t1 * scale, t2 * scale
                spring[p, 0], spring[p, 1], spring[p, 2] = t0, t1, t2
                g0, g1, g2 = t0 - fn * u0, t1 - fn * u1, t2 - fn * u2
                f[i, 0] += g0
                f[i, 1] += g1
                f[i, 2] += g2
                f[j, 0] -= g0
                f[j, 1] -= g1
                f[j, 2] -= g2
            if k_phase >= n_phase:
                largest = 0.0
                for h in range(n_involved):
                    g = grains[h]
                    for a in range(3):
                        if dynamic[g, a]:
                            largest = max(largest, abs(f[g, a]))
                if largest <= limit or k >= max_substeps:
                    break
            k += 1
            if k_phase < n_phase:
                k_phase += 1
                s = k_phase * ds if k_phase < n_phase else 1.0
            for h in range(n_involved):  # leapfrog with Cundall damping; the grains no relevant pair touches are never read
                g = grains[h]
                unloaded = f[g, 0] == 0.0 and f[g, 1] == 0.0 and f[g, 2] == 0.0
                for a in range(3):
                    if dynamic[g, a]:
                        if unloaded:
                            v[g, a] = 0.0
                        else:
                            accel = f[g, a] * inv_mass[g]
                            power = f[g, a] * (v[g, a] + 0.5 * dt * accel)
                            sign = 1.0 if power > 0.0 else (-1.0 if power < 0.0 else 0.0)
                            v[g, a] = v[g, a] + dt * (accel * (1.0 - damping * sign))
                        dx[g, a] = v[g, a] * dt
                        x[g, a] += dx[g, a]
                    else:
                        target = x0[c, g, a] + s * (x1[c, g, a] - x0[c, g, a])
                        dx[g, a] = target - x[g, a]
                        x[g, a] = target
        for g in range(n_grains):
            for a in range(3):
                x_out[c, g, a] = x[g, a] if involved[g] else x0[c, g, a] + (x1[c, g, a] - x0[c, g, a])
        substeps_out[c] = k
