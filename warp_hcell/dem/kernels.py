"""Warp code of the planar meso-DEM: the batched cell-step kernel (float64); the contact law is
``warp_hcell.dem.contact``.

One thread advances one cell through a whole strain increment: the substep loop runs
inside the kernel and the cell (positions, velocities, displacements, shear forces) lives in
fixed-size local vectors. Kernels are generated per topology (candidate pairs and driven
DOF mask are compile-time constants), so every grain/pair index is static and the loops are
unrolled; ``step_kernel`` caches one kernel per topology. Measured on the H-cell (CPU, one
thread, 1e5 cells): 1.9e7 cell-substeps per CPU-second, 1.8 times the same kernel reading
the pair and driven tables from arrays in rolled loops (bit-identical results).

Conventions inside the kernels (tension-positive DEM quantities, local frame (n, t)):
    - pair p = (i, j): unit normal ``u = (x_j - x_i) / |x_j - x_i|``, tangent w = (-u_t, u_n);
    - ``contact_force[p]`` is the force exerted ON grain i BY grain j: -f_n u + f_s w,
      with f_n >= 0 the normal (repulsive) force and f_s the tangential spring force
      (``shear_force``), which grows by kt * ((dx_j - dx_i) . w);
    - a pair is in contact when its gap is <= contact_tolerance * (r_i + r_j); a contact with
      a gap >= 0 carries zero force (and so zero shear force); out of contact the shear
      history is reset;
    - free DOFs: explicit (leapfrog) integration with Cundall local damping
      (``damped_velocity``), from rest at the start of each increment; a free grain whose net
      force is exactly zero is set at rest (no drift of unloaded grains in mechanism states);
    - driven DOFs: x = x_ref * l(s) / l_ref with l(s) moving linearly from the old to the new
      cell size, s = min(k rate / max|d_eps|, 1) over n = ceil(max|d_eps| / rate) driving
      substeps (the last one shorter: the driven path is continuous in d_eps); then relaxation
      until max free-DOF force <= force_tolerance * max(max normal force, force_floor), or
      max_substeps;
    - memory: the velocities in the state are every grain's mean velocity over the last
      increment's driving substeps (driven DOFs: the last driving rate; free DOFs: how they
      moved while the cell was driven, relaxation included);
    - adaptive rate and prediction, from the cell's own state only (no knowledge of the
      mesostructure): if the new increment, driven at strain_per_substep, continues the last
      one (same direction within velocity_change), the rate may grow by rate_growth over the
      last driving rate, up to strain_per_substep, and the free grains drift with the driven
      ones by what they did in the last increment, scaled like the driven displacements. A new
      direction (start of shear, reversal, a probe) starts again from
      refined_strain_per_substep without prediction. Within an increment, once a contact
      opens, closes, starts or stops sliding, the rest is driven at refined_strain_per_substep.

The conversion to compression-positive quantities happens on the host
(``warp_hcell.database.learning_state.to_compression_positive``).
"""

from __future__ import annotations

import functools

import warp as wp

from warp_hcell.dem.contact import contact_law, contact_regime, normal_force

wp.set_module_options({"enable_backward": False})


@wp.func
def damped_velocity(
    force: wp.float64,
    velocity: wp.float64,
    inv_mass: wp.float64,
    dt: wp.float64,
    damping: wp.float64,
):
    """Leapfrog velocity update of one free DOF with Cundall local (non-viscous) damping.

    Args:
        force: net force on the DOF [N]; velocity: v(t - dt/2) [m/s]; inv_mass [1/kg];
        dt: time step [s]; damping: Cundall coefficient [-].

    Returns:
        v(t + dt/2) = v + dt f/m (1 - damping sign(f v(t))), v(t) estimated as v + dt/2 f/m.
    """
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    accel = force * inv_mass
    power = force * (velocity + wp.float64(0.5) * dt * accel)
    sign = wp.where(power > zero, one, wp.where(power < zero, -one, zero))
    return velocity + dt * (accel * (one - damping * sign))


@functools.lru_cache(maxsize=None)
def step_kernel(pairs: tuple[tuple[int, int], ...], driven: tuple[tuple[bool, bool], ...],
                outer: tuple[int, ...]) -> wp.Kernel:
    """The cell-step kernel for one topology.

    Args:
        pairs: candidate contact pairs (i, j), 0-based, i < j.
        driven: per grain, (driven along n, driven along t).
        outer: ordered grain indices of the polygon whose area is V_cell.

    Returns:
        A kernel launched with one thread per cell of cells [first_cell, first_cell + dim)
        (see ``integrator.launch_step``).
    """
    n_grains = len(driven)
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    drive_n = tuple(bool(d[0]) for d in driven)
    drive_t = tuple(bool(d[1]) for d in driven)
    n_outer = len(outer)
    outer_next = tuple(outer[(k + 1) % n_outer] for k in range(n_outer))
    vec_g = wp.types.vector(length=n_grains, dtype=wp.float64)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)

    @wp.kernel(module="unique", module_options={"enable_backward": False, "max_unroll": 4096, "fuse_fp": False})
    def dem_step(
        radius: wp.array2d(dtype=wp.float64),
        inv_mass: wp.array2d(dtype=wp.float64),
        reference_position: wp.array2d(dtype=wp.vec2d),
        reference_cell_size: wp.array(dtype=wp.vec2d),
        dt: wp.array(dtype=wp.float64),
        force_floor: wp.array(dtype=wp.float64),
        kn: wp.float64,
        kt: wp.float64,
        mu: wp.float64,
        damping: wp.float64,
        contact_tolerance: wp.float64,
        strain_per_substep: wp.float64,
        refined_strain_per_substep: wp.float64,
        velocity_change: wp.float64,
        rate_growth: wp.float64,
        force_tolerance: wp.float64,
        max_substeps: wp.int32,
        position_in: wp.array2d(dtype=wp.vec2d),
        velocity_in: wp.array2d(dtype=wp.vec2d),
        shear_force_in: wp.array2d(dtype=wp.float64),
        cell_size_in: wp.array(dtype=wp.vec2d),
        d_eps_local: wp.array(dtype=wp.vec2d),
        first_cell: wp.int32,
        # outputs
        position_out: wp.array2d(dtype=wp.vec2d),
        velocity_out: wp.array2d(dtype=wp.vec2d),
        shear_force_out: wp.array2d(dtype=wp.float64),
        contact_force_out: wp.array2d(dtype=wp.vec2d),
        contact_out: wp.array2d(dtype=wp.int32),
        cell_size_out: wp.array(dtype=wp.vec2d),
        moment_out: wp.array(dtype=wp.mat22d),
        area_out: wp.array(dtype=wp.float64),
        substeps_out: wp.array(dtype=wp.int32),
        converged_out: wp.array(dtype=wp.int32),
    ):
        c = first_cell + wp.tid()
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        h = dt[c]
        floor = force_floor[c]

        xn = vec_g()
        xt = vec_g()
        vn = vec_g()
        vt = vec_g()
        dxn = vec_g()
        dxt = vec_g()
        fn_g = vec_g()
        ft_g = vec_g()
        refn = vec_g()
        reft = vec_g()
        im = vec_g()
        x0n = vec_g()
        x0t = vec_g()
        driftn = vec_g()
        driftt = vec_g()
        for g in range(wp.static(n_grains)):
            x0 = position_in[c, g]
            v0 = velocity_in[c, g]
            r0 = reference_position[c, g]
            xn[g] = x0[0]
            xt[g] = x0[1]
            x0n[g] = x0[0]
            x0t[g] = x0[1]
            vn[g] = v0[0]
            vt[g] = v0[1]
            refn[g] = r0[0]
            reft[g] = r0[1]
            im[g] = inv_mass[c, g]

        fs = vec_p()
        rsum = vec_p()
        cut2 = vec_p()
        was_regime = vec_p()
        widen = one + contact_tolerance
        for p in range(wp.static(n_pairs)):
            fs[p] = shear_force_in[c, p]
            r_sum = radius[c, wp.static(pi[p])] + radius[c, wp.static(pj[p])]
            rsum[p] = r_sum
            cut2[p] = (r_sum * widen) * (r_sum * widen)

        # driven coordinates follow l(s) = l_start + (l_end - l_start) s, s = s_base + k ds: every
        # driving substep moves the cell by the rate, the last one by what is left (the path
        # of the driven DOFs then depends continuously on d_eps)
        l_ref = reference_cell_size[c]
        l_start = cell_size_in[c]
        de = d_eps_local[c]
        l_end = wp.vec2d(l_start[0] * (one - de[0]), l_start[1] * (one - de[1]))
        largest = wp.max(wp.abs(de[0]), wp.abs(de[1]))
        n_phase = wp.int32(wp.ceil(largest / strain_per_substep))
        scale_n0 = l_start[0] / l_ref[0]
        scale_t0 = l_start[1] / l_ref[1]
        dscale_n = (l_end[0] - l_start[0]) / l_ref[0]
        dscale_t = (l_end[1] - l_start[1]) / l_ref[1]
        # strain per substep and predictor from the cell's own state. The state's velocities are
        # every grain's mean velocity over the last increment's driving substeps; for the driven
        # DOFs, d_last = v h is the last driving rate per substep, D_new this increment's
        # displacement and d_new = D_new / n its displacement per substep at the coarse rate.
        # lam = (d_last . d_new) / (d_new . d_new). The new increment continues the last one when
        # |d_last - lam d_new| <= velocity_change lam |d_new| (max norms); then
        # - the rate may grow by rate_growth over the last one, up to strain_per_substep
        #   (otherwise the free grains moved for another path: refined_strain_per_substep);
        # - the free grains are predicted to move as they did, scaled like the driven ones:
        #   by span v_last, span = (v_last . D_new) / (v_last . v_last) [s] over the driven DOFs,
        #   in step with them (span v_last ds per unit of the driving parameter s). The damped
        #   dynamics, started from rest, corrects what the prediction misses.
        inv_n_coarse = one / wp.float64(wp.max(n_phase, 1))
        dot = zero
        norm2 = zero
        dot_v = zero
        norm_v = zero
        for g in range(wp.static(n_grains)):
            if wp.static(drive_n[g]):
                d_new = refn[g] * dscale_n * inv_n_coarse
                dot = dot + vn[g] * h * d_new
                norm2 = norm2 + d_new * d_new
                dot_v = dot_v + vn[g] * (refn[g] * dscale_n)
                norm_v = norm_v + vn[g] * vn[g]
            if wp.static(drive_t[g]):
                d_new = reft[g] * dscale_t * inv_n_coarse
                dot = dot + vt[g] * h * d_new
                norm2 = norm2 + d_new * d_new
                dot_v = dot_v + vt[g] * (reft[g] * dscale_t)
                norm_v = norm_v + vt[g] * vt[g]
        lam = wp.where(norm2 > zero, dot / wp.where(norm2 > zero, norm2, one), zero)
        off = zero
        drive = zero
        for g in range(wp.static(n_grains)):
            if wp.static(drive_n[g]):
                d_new = refn[g] * dscale_n * inv_n_coarse
                off = wp.max(off, wp.abs(vn[g] * h - lam * d_new))
                drive = wp.max(drive, wp.abs(d_new))
            if wp.static(drive_t[g]):
                d_new = reft[g] * dscale_t * inv_n_coarse
                off = wp.max(off, wp.abs(vt[g] * h - lam * d_new))
                drive = wp.max(drive, wp.abs(d_new))
        steady = lam > zero and off <= velocity_change * lam * drive
        rate = refined_strain_per_substep
        if steady:
            rate = wp.min(strain_per_substep, wp.max(refined_strain_per_substep, rate_growth * lam * largest * inv_n_coarse))
        n_phase = wp.int32(wp.ceil(largest / rate))
        ds = wp.where(largest > zero, rate / wp.where(largest > zero, largest, one), zero)
        span = wp.where(steady and norm_v > zero, dot_v / wp.where(norm_v > zero, norm_v, one), zero)
        for g in range(wp.static(n_grains)):
            if wp.static(not drive_n[g]):
                driftn[g] = span * vn[g]
                vn[g] = zero
            if wp.static(not drive_t[g]):
                driftt[g] = span * vt[g]
                vt[g] = zero
        s_base = zero
        s = zero
        s_prev = zero
        k_phase = wp.int32(0)
        refined = wp.int32(0)

        substeps = wp.int32(0)
        driving = wp.int32(0)
        converged = wp.int32(0)
        while True:
            # contact forces at the current positions (shear increment from the last move);
            # regime of each pair: 0 open, 1 sticking, 2 sliding (force at the Coulomb cap);
            # changed = 1 if a regime changed since the last evaluation
            fmax = zero
            changed = wp.int32(0)
            for g in range(wp.static(n_grains)):
                fn_g[g] = zero
                ft_g[g] = zero
            for p in range(wp.static(n_pairs)):
                i = wp.static(pi[p])
                j = wp.static(pj[p])
                bn = xn[j] - xn[i]
                bt = xt[j] - xt[i]
                dist2 = bn * bn + bt * bt
                regime = zero
                if dist2 <= cut2[p]:
                    dist = wp.sqrt(dist2)
                    inv_dist = one / dist
                    un = bn * inv_dist
                    ut = bt * inv_dist
                    du = (dxt[j] - dxt[i]) * un - (dxn[j] - dxn[i]) * ut
                    normal, shear = contact_law(rsum[p] - dist, du, fs[p], kn, kt, mu)
                    fs[p] = shear
                    regime = contact_regime(normal, wp.abs(shear), mu * normal)
                    fin = -normal * un - shear * ut
                    fit = -normal * ut + shear * un
                    fn_g[i] = fn_g[i] + fin
                    ft_g[i] = ft_g[i] + fit
                    fn_g[j] = fn_g[j] - fin
                    ft_g[j] = ft_g[j] - fit
                    fmax = wp.where(normal > fmax, normal, fmax)
                else:
                    fs[p] = zero
                changed = wp.where(substeps > 0 and regime != was_regime[p], 1, changed)
                was_regime[p] = regime

            if k_phase < n_phase:
                # adaptive driving: once a contact has opened, closed, started or stopped
                # sliding, the rest of the increment is driven at refined_strain_per_substep
                if changed == 1 and refined == 0:
                    refined = 1
                    n_rest = wp.int32(wp.ceil((one - s) * largest / refined_strain_per_substep))
                    if n_rest > n_phase - k_phase:
                        s_base = s
                        ds = refined_strain_per_substep / largest
                        n_phase = n_rest
                        k_phase = 0
            else:
                unbalanced = zero
                for g in range(wp.static(n_grains)):
                    if wp.static(not drive_n[g]):
                        unbalanced = wp.where(wp.abs(fn_g[g]) > unbalanced, wp.abs(fn_g[g]), unbalanced)
                    if wp.static(not drive_t[g]):
                        unbalanced = wp.where(wp.abs(ft_g[g]) > unbalanced, wp.abs(ft_g[g]), unbalanced)
                if unbalanced <= force_tolerance * wp.where(fmax > floor, fmax, floor):
                    converged = 1
                    break
                if substeps >= max_substeps:
                    break

            substeps += 1
            s_prev = s
            if k_phase < n_phase:
                k_phase += 1
                driving += 1
                s = wp.where(k_phase < n_phase, wp.min(s_base + wp.float64(k_phase) * ds, one), one)
            scale_n = scale_n0 + dscale_n * s
            scale_t = scale_t0 + dscale_t * s
            for g in range(wp.static(n_grains)):
                unloaded = fn_g[g] == zero and ft_g[g] == zero
                if wp.static(drive_n[g]):
                    x_new = refn[g] * scale_n
                    dxn[g] = x_new - xn[g]
                    xn[g] = x_new
                else:
                    v = wp.where(unloaded, zero, damped_velocity(fn_g[g], vn[g], im[g], h, damping))
                    vn[g] = v
                    move = v * h + wp.where(unloaded, zero, driftn[g] * (s - s_prev))
                    dxn[g] = move
                    xn[g] = xn[g] + move
                if wp.static(drive_t[g]):
                    x_new = reft[g] * scale_t
                    dxt[g] = x_new - xt[g]
                    xt[g] = x_new
                else:
                    v = wp.where(unloaded, zero, damped_velocity(ft_g[g], vt[g], im[g], h, damping))
                    vt[g] = v
                    move = v * h + wp.where(unloaded, zero, driftt[g] * (s - s_prev))
                    dxt[g] = move
                    xt[g] = xt[g] + move

        for g in range(wp.static(n_grains)):
            position_out[c, g] = wp.vec2d(xn[g], xt[g])
            # every grain's mean velocity over the increment's driving substeps: the memory from
            # which the next increment sets its strain per substep and its predictor
            if wp.static(drive_n[g]):
                vn[g] = wp.where(driving > 0, refn[g] * dscale_n / (wp.float64(driving) * h), zero)
            else:
                vn[g] = wp.where(driving > 0, (xn[g] - x0n[g]) / (wp.float64(driving) * h), zero)
            if wp.static(drive_t[g]):
                vt[g] = wp.where(driving > 0, reft[g] * dscale_t / (wp.float64(driving) * h), zero)
            else:
                vt[g] = wp.where(driving > 0, (xt[g] - x0t[g]) / (wp.float64(driving) * h), zero)
            velocity_out[c, g] = wp.vec2d(vn[g], vt[g])
        # Love-Weber sum (tension positive) over the pairs: sum_p f_p (x) (x_j - x_i)
        m_nn = zero
        m_nt = zero
        m_tn = zero
        m_tt = zero
        for p in range(wp.static(n_pairs)):
            shear_force_out[c, p] = fs[p]
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            bn = xn[j] - xn[i]
            bt = xt[j] - xt[i]
            dist2 = bn * bn + bt * bt
            dist = wp.sqrt(dist2)
            un = bn / dist
            ut = bt / dist
            # the last force evaluation ran at these positions: same contacts, same normal forces
            touching = dist2 <= cut2[p]
            normal = wp.where(touching, normal_force(rsum[p] - dist, kn), zero)
            f_n = -normal * un - fs[p] * ut
            f_t = -normal * ut + fs[p] * un
            contact_force_out[c, p] = wp.vec2d(f_n, f_t)
            contact_out[c, p] = wp.where(touching, 1, 0)
            m_nn = m_nn + f_n * bn
            m_nt = m_nt + f_n * bt
            m_tn = m_tn + f_t * bn
            m_tt = m_tt + f_t * bt
        moment_out[c] = wp.mat22d(m_nn, m_nt, m_tn, m_tt)
        # V_cell: shoelace formula over the outer polygon
        twice_area = zero
        for k in range(wp.static(n_outer)):
            a = wp.static(outer[k])
            b = wp.static(outer_next[k])
            twice_area = twice_area + (xn[a] * xt[b] - xn[b] * xt[a])
        area_out[c] = wp.float64(0.5) * wp.abs(twice_area)
        cell_size_out[c] = l_end
        substeps_out[c] = substeps
        converged_out[c] = converged

    return dem_step
