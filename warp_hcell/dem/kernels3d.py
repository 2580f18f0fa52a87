"""Warp code of the 3D meso-DEM: the batched cell-step kernel for cells of spheres (float64).

The 3D counterpart of ``warp_hcell.dem.kernels`` (same stepping, same conventions), one thread
per cell with the whole increment inside the kernel and the cell in fixed-size local
matrices; kernels are generated per topology (candidate pairs, driven DOF mask and outer
faces are compile-time constants, loops unrolled). The stepping is the 2D kernel's
(``warp_hcell.dem.stepping``); the pairs and the volume are below.

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

import functools

import warp as wp

from warp_hcell.dem.contact import carried_spring, contact_law_3d, normal_force
from warp_hcell.dem.stepping import cell_step_kernel, grain_matrix, mask_code, pair_setup

wp.set_module_options({"enable_backward": False})

DIM = 3
"""Spatial dimension of the cells this module steps."""


@functools.lru_cache(maxsize=None)
def pair_pieces_3d(pairs: tuple[tuple[int, int], ...], n_grains: int) -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``setup``, ``forces``, ``output``) of the spatial pairs, as ``kernels.pair_pieces`` in the plane;
    the shear force of a pair is a vector (a row of an (n_pairs, 3) matrix)."""
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    mat = grain_matrix(n_grains, DIM)
    mat_p = grain_matrix(n_pairs, DIM)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)
    code = mask_code(pairs)

    setup = pair_setup(pairs, DIM)

    @wp.func
    def forces(x: mat, dx: mat, fs: mat_p, rsum: vec_p, cut2: vec_p, was_regime: vec_p, substeps: wp.int32,
               kn: wp.float64, kt: wp.float64, mu: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        f = mat()
        shear_new = mat_p()
        regime_new = vec_p()
        fmax = zero
        changed = wp.int32(0)
        for p in range(wp.static(n_pairs)):
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            b = wp.vec3d(x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2])
            dist2 = wp.dot(b, b)
            regime = zero
            if dist2 <= cut2[p]:
                dist = wp.sqrt(dist2)
                u = b * (wp.float64(1.0) / dist)
                rel = wp.vec3d(dx[j, 0] - dx[i, 0], dx[j, 1] - dx[i, 1], dx[j, 2] - dx[i, 2])
                du = rel - wp.dot(rel, u) * u
                carried = carried_spring(wp.vec3d(fs[p, 0], fs[p, 1], fs[p, 2]), u)
                normal, shear, regime = contact_law_3d(rsum[p] - dist, du, carried, kn, kt, mu)
                force = shear - normal * u
                for a in range(wp.static(DIM)):
                    shear_new[p, a] = shear[a]
                    f[i, a] = f[i, a] + force[a]
                    f[j, a] = f[j, a] - force[a]
                fmax = wp.where(normal > fmax, normal, fmax)
            changed = wp.where(substeps > 0 and regime != was_regime[p], 1, changed)
            regime_new[p] = regime
        return f, shear_new, regime_new, fmax, changed

    @wp.func
    def output(x: mat, fs: mat_p, rsum: vec_p, cut2: vec_p, kn: wp.float64,
               shear_force_out: wp.array2d(dtype=wp.vec3d), contact_force_out: wp.array2d(dtype=wp.vec3d),
               contact_out: wp.array2d(dtype=wp.int32), c: wp.int32):
        wp.static(code)
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
            normal = wp.where(touching, normal_force(rsum[p] - dist, kn), wp.float64(0.0))
            force = shear - normal * u
            contact_force_out[c, p] = force
            contact_out[c, p] = wp.where(touching, 1, 0)
            moment = moment + wp.outer(force, b)
        return moment

    return setup, forces, output


@functools.lru_cache(maxsize=None)
def polyhedron_volume(faces: tuple[tuple[int, int, int], ...], n_grains: int) -> wp.Function:
    """``volume(x)``: V_cell [m^3] of the outer faces, abs(sum_f x_a . (x_b x x_c)) / 6."""
    mat = grain_matrix(n_grains, DIM)
    code = mask_code(faces)

    @wp.func
    def volume(x: mat):
        wp.static(code)
        six_volume = wp.float64(0.0)
        for k in range(wp.static(len(faces))):
            fa = wp.static(faces[k][0])
            fb = wp.static(faces[k][1])
            fc = wp.static(faces[k][2])
            xa = wp.vec3d(x[fa, 0], x[fa, 1], x[fa, 2])
            xb = wp.vec3d(x[fb, 0], x[fb, 1], x[fb, 2])
            xc = wp.vec3d(x[fc, 0], x[fc, 1], x[fc, 2])
            six_volume = six_volume + wp.dot(xa, wp.cross(xb, xc))
        return wp.abs(six_volume) / wp.float64(6.0)

    return volume


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
    drive = tuple(tuple(bool(v) for v in d) for d in driven)
    n_grains = len(drive)
    return cell_step_kernel(drive, len(pairs), pair_pieces_3d(pairs, n_grains), polyhedron_volume(faces, n_grains),
                            8192)
