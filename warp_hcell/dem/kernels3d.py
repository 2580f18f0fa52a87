"""Warp code of the 3D meso-DEM: the batched cell-step kernel for cells of spheres (float64).

The 3D counterpart of ``warp_hcell.dem.kernels`` (same stepping, same conventions), one thread
per cell with the whole increment inside the kernel and the cell in fixed-size local
matrices; kernels are generated per topology (candidate pairs, driven DOF mask and outer
faces are compile-time constants, loops unrolled).

Conventions inside the kernel (tension-positive DEM quantities, local frame (n, t1, t2)):
    - pair p = (i, j): unit normal u = (x_j - x_i) / norm(x_j - x_i);
    - ``shear_force[p]`` is the tangential spring force ON grain i, a vector in the contact's
      tangent plane; ``contact_force[p]`` = -f_n u + f_s is the force on grain i by grain j,
      f_n >= 0 the normal (repulsive) force;
    - each substep the spring is first carried into the current tangent plane (projected on
      it and rescaled to its former magnitude: a rotation for the small changes of u of one
      substep; for a contact whose relative motion stays in one plane this is exactly the
      scalar spring of the 2D kernel), then grows by kt times the tangential part of the
      relative displacement (dx_j - dx_i); the trial force is capped at mu f_n along its own
      direction (Coulomb); out of contact the history is reset;
    - contact when the gap is <= contact_tolerance (r_i + r_j); a contact with a gap >= 0
      carries zero force;
    - free DOFs: leapfrog with Cundall local damping per component, from rest at the start of
      each increment (plus the predicted drift); a free grain whose net force is exactly zero
      is held at rest;
    - driven DOFs: x_a = x_a,ref l_a(s) / l_a,ref, l(s) linear from the old to the new cell size
      over the driving substeps; then relaxation until max free-DOF force <= force_tolerance *
      max(max normal force, force_floor), or max_substeps;
    - adaptive rate, prediction of the free grains and refinement on regime changes (a contact
      opening, closing, starting or stopping sliding) exactly as in the 2D kernel;
    - cell volume: the polyhedron of the outer faces (triangles of grain centres, oriented
      outwards), V = abs(sum_f x_a . (x_b x x_c)) / 6.
"""

from __future__ import annotations

import functools

import warp as wp

from warp_hcell.dem.contact import carried_spring, contact_law_3d, normal_force
from warp_hcell.dem.kernels import damped_velocity

wp.set_module_options({"enable_backward": False})

DIM = 3
"""Spatial dimension of the cells this module steps."""


@functools.lru_cache(maxsize=None)
def step_kernel_3d(pairs: tuple[tuple[int, int], ...], driven: tuple[tuple[bool, bool, bool], ...],
                   faces: tuple[tuple[int, int, int], ...]) -> wp.Kernel:
    """The 3D cell-step kernel for one topology.

    Args:
        pairs: candidate contact pairs (i, j), 0-based, i < j.
        driven: per grain, driven along (n, t1, t2).
        faces: outer triangles (a, b, c) of grain indices, oriented outwards (volume V_cell).

    Returns:
        A kernel launched with one thread per cell of cells [first_cell, first_cell + dim).
    """
    n_grains = len(driven)
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    drive = tuple(tuple(bool(v) for v in d) for d in driven)
    mat_g = wp.types.matrix(shape=(n_grains, DIM), dtype=wp.float64)
    mat_p = wp.types.matrix(shape=(n_pairs, DIM), dtype=wp.float64)
    vec_g = wp.types.vector(length=n_grains, dtype=wp.float64)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)

    @wp.kernel(module="unique", module_options={"enable_backward": False, "max_unroll": 8192, "fuse_fp": False})
    def dem_step_3d(
        radius: wp.array2d(dtype=wp.float64),
        inv_mass: wp.array2d(dtype=wp.float64),
        reference_position: wp.array2d(dtype=wp.vec3d),
        reference_cell_size: wp.array(dtype=wp.vec3d),
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
        position_in: wp.array2d(dtype=wp.vec3d),
        velocity_in: wp.array2d(dtype=wp.vec3d),
        shear_force_in: wp.array2d(dtype=wp.vec3d),
        cell_size_in: wp.array(dtype=wp.vec3d),
        d_eps_local: wp.array(dtype=wp.vec3d),
        first_cell: wp.int32,
        # outputs
        position_out: wp.array2d(dtype=wp.vec3d),
        velocity_out: wp.array2d(dtype=wp.vec3d),
        shear_force_out: wp.array2d(dtype=wp.vec3d),
        contact_force_out: wp.array2d(dtype=wp.vec3d),
        contact_out: wp.array2d(dtype=wp.int32),
        cell_size_out: wp.array(dtype=wp.vec3d),
        moment_out: wp.array(dtype=wp.mat33d),
        volume_out: wp.array(dtype=wp.float64),
        substeps_out: wp.array(dtype=wp.int32),
        converged_out: wp.array(dtype=wp.int32),
    ):
        c = first_cell + wp.tid()
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        h = dt[c]
        floor = force_floor[c]

        x = mat_g()
        v = mat_g()
        dx = mat_g()
        f = mat_g()
        ref = mat_g()
        x0 = mat_g()
        drift = mat_g()
        im = vec_g()
        for g in range(wp.static(n_grains)):
            p0 = position_in[c, g]
            q0 = velocity_in[c, g]
            r0 = reference_position[c, g]
            for a in range(wp.static(DIM)):
                x[g, a] = p0[a]
                x0[g, a] = p0[a]
                v[g, a] = q0[a]
                ref[g, a] = r0[a]
            im[g] = inv_mass[c, g]

        fs = mat_p()
        rsum = vec_p()
        cut2 = vec_p()
        was_regime = vec_p()
        widen = one + contact_tolerance
        for p in range(wp.static(n_pairs)):
            s0 = shear_force_in[c, p]
            for a in range(wp.static(DIM)):
                fs[p, a] = s0[a]
            r_sum = radius[c, wp.static(pi[p])] + radius[c, wp.static(pj[p])]
            rsum[p] = r_sum
            cut2[p] = (r_sum * widen) * (r_sum * widen)

        l_ref = reference_cell_size[c]
        l_start = cell_size_in[c]
        de = d_eps_local[c]
        l_end = wp.vec3d(l_start[0] * (one - de[0]), l_start[1] * (one - de[1]), l_start[2] * (one - de[2]))
        largest = wp.max(wp.max(wp.abs(de[0]), wp.abs(de[1])), wp.abs(de[2]))
        n_phase = wp.int32(wp.ceil(largest / strain_per_substep))
        scale0 = wp.vec3d(l_start[0] / l_ref[0], l_start[1] / l_ref[1], l_start[2] / l_ref[2])
        dscale = wp.vec3d((l_end[0] - l_start[0]) / l_ref[0], (l_end[1] - l_start[1]) / l_ref[1],
                          (l_end[2] - l_start[2]) / l_ref[2])
        # rate and predictor from the cell's own state (warp_hcell.dem.kernels for the reasoning)
        inv_n_coarse = one / wp.float64(wp.max(n_phase, 1))
        dot = zero
        norm2 = zero
        dot_v = zero
        norm_v = zero
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(DIM)):
                if wp.static(drive[g][a]):
                    d_new = ref[g, a] * dscale[a] * inv_n_coarse
                    dot = dot + v[g, a] * h * d_new
                    norm2 = norm2 + d_new * d_new
                    dot_v = dot_v + v[g, a] * (ref[g, a] * dscale[a])
                    norm_v = norm_v + v[g, a] * v[g, a]
        lam = wp.where(norm2 > zero, dot / wp.where(norm2 > zero, norm2, one), zero)
        off = zero
        driving_size = zero
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(DIM)):
                if wp.static(drive[g][a]):
                    d_new = ref[g, a] * dscale[a] * inv_n_coarse
                    off = wp.max(off, wp.abs(v[g, a] * h - lam * d_new))
                    driving_size = wp.max(driving_size, wp.abs(d_new))
        steady = lam > zero and off <= velocity_change * lam * driving_size
        rate = refined_strain_per_substep
        if steady:
            rate = wp.min(strain_per_substep, wp.max(refined_strain_per_substep, rate_growth * lam * largest * inv_n_coarse))
        n_phase = wp.int32(wp.ceil(largest / rate))
        ds = wp.where(largest > zero, rate / wp.where(largest > zero, largest, one), zero)
        span = wp.where(steady and norm_v > zero, dot_v / wp.where(norm_v > zero, norm_v, one), zero)
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(DIM)):
                if wp.static(not drive[g][a]):
                    drift[g, a] = span * v[g, a]
                    v[g, a] = zero
        s_base = zero
        s = zero
        s_prev = zero
        k_phase = wp.int32(0)
        refined = wp.int32(0)

        substeps = wp.int32(0)
        driving = wp.int32(0)
        converged = wp.int32(0)
        while True:
            # contact forces at the current positions; regime 0 open, 1 sticking, 2 sliding
            fmax = zero
            changed = wp.int32(0)
            for g in range(wp.static(n_grains)):
                for a in range(wp.static(DIM)):
                    f[g, a] = zero
            for p in range(wp.static(n_pairs)):
                i = wp.static(pi[p])
                j = wp.static(pj[p])
                b = wp.vec3d(x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2])
                dist2 = wp.dot(b, b)
                regime = zero
                if dist2 <= cut2[p]:
                    dist = wp.sqrt(dist2)
                    u = b * (one / dist)
                    rel = wp.vec3d(dx[j, 0] - dx[i, 0], dx[j, 1] - dx[i, 1], dx[j, 2] - dx[i, 2])
                    du = rel - wp.dot(rel, u) * u
                    carried = carried_spring(wp.vec3d(fs[p, 0], fs[p, 1], fs[p, 2]), u)
                    normal, shear, regime = contact_law_3d(rsum[p] - dist, du, carried, kn, kt, mu)
                    for a in range(wp.static(DIM)):
                        fs[p, a] = shear[a]
                    force = shear - normal * u
                    for a in range(wp.static(DIM)):
                        f[i, a] = f[i, a] + force[a]
                        f[j, a] = f[j, a] - force[a]
                    fmax = wp.where(normal > fmax, normal, fmax)
                else:
                    for a in range(wp.static(DIM)):
                        fs[p, a] = zero
                changed = wp.where(substeps > 0 and regime != was_regime[p], 1, changed)
                was_regime[p] = regime

            if k_phase < n_phase:
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
                    for a in range(wp.static(DIM)):
                        if wp.static(not drive[g][a]):
                            unbalanced = wp.where(wp.abs(f[g, a]) > unbalanced, wp.abs(f[g, a]), unbalanced)
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
            for g in range(wp.static(n_grains)):
                unloaded = f[g, 0] == zero and f[g, 1] == zero and f[g, 2] == zero
                for a in range(wp.static(DIM)):
                    if wp.static(drive[g][a]):
                        x_new = ref[g, a] * (scale0[a] + dscale[a] * s)
                        dx[g, a] = x_new - x[g, a]
                        x[g, a] = x_new
                    else:
                        vel = wp.where(unloaded, zero, damped_velocity(f[g, a], v[g, a], im[g], h, damping))
                        v[g, a] = vel
                        move = vel * h + wp.where(unloaded, zero, drift[g, a] * (s - s_prev))
                        dx[g, a] = move
                        x[g, a] = x[g, a] + move

        for g in range(wp.static(n_grains)):
            position_out[c, g] = wp.vec3d(x[g, 0], x[g, 1], x[g, 2])
            for a in range(wp.static(DIM)):
                if wp.static(drive[g][a]):
                    v[g, a] = wp.where(driving > 0, ref[g, a] * dscale[a] / (wp.float64(driving) * h), zero)
                else:
                    v[g, a] = wp.where(driving > 0, (x[g, a] - x0[g, a]) / (wp.float64(driving) * h), zero)
            velocity_out[c, g] = wp.vec3d(v[g, 0], v[g, 1], v[g, 2])
        moment = wp.mat33d()
        for p in range(wp.static(n_pairs)):
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            shear = wp.vec3d(fs[p, 0], fs[p, 1], fs[p, 2])
            shear_force_out[c, p] = shear
            b = wp.vec3d(x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2])
            dist2 = wp.dot(b, b)
            dist = wp.sqrt(dist2)
            u = b / dist
            touching = dist2 <= cut2[p]
            normal = wp.where(touching, normal_force(rsum[p] - dist, kn), zero)
            force = shear - normal * u
            contact_force_out[c, p] = force
            contact_out[c, p] = wp.where(touching, 1, 0)
            moment = moment + wp.outer(force, b)
        moment_out[c] = moment
        six_volume = zero
        for k in range(wp.static(len(faces))):
            fa = wp.static(faces[k][0])
            fb = wp.static(faces[k][1])
            fc = wp.static(faces[k][2])
            xa = wp.vec3d(x[fa, 0], x[fa, 1], x[fa, 2])
            xb = wp.vec3d(x[fb, 0], x[fb, 1], x[fb, 2])
            xc = wp.vec3d(x[fc, 0], x[fc, 1], x[fc, 2])
            six_volume = six_volume + wp.dot(xa, wp.cross(xb, xc))
        volume_out[c] = wp.abs(six_volume) / wp.float64(6.0)
        cell_size_out[c] = l_end
        substeps_out[c] = substeps
        converged_out[c] = converged

    return dem_step_3d
