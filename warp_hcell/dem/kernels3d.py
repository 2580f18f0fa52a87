"""Warp code of the 3D meso-DEM: the batched cell-step kernel for cells of spheres (float64).

The 3D counterpart of ``warp_hcell.dem.kernels`` (same stepping, same conventions): one thread per
cell, the whole increment inside the kernel, kernels generated per topology (candidate pairs,
driven DOF mask and outer faces are compile-time constants). The stepping
(``warp_hcell.dem.stepping``) and pair loops (``warp_hcell.dem.pairs``) are the 2D kernel's, the
law of one spatial pair the contact law's (``warp_hcell.dem.laws``: ``spatial_contact``); the
pair force and the volume are below.

Conventions inside the kernel (tension-positive DEM quantities, local frame (n, t1, t2)):
    - pair p = (i, j): unit normal u = (x_j - x_i) / norm(x_j - x_i);
    - ``shear_force[p]`` is the tangential spring force ON grain i, a vector in the tangent
      plane; ``contact_force[p]`` = -f_n u + f_s is the force on grain i by grain j, f_n >= 0;
    - each substep the spring is carried into the current tangent plane (projected and rescaled
      to its former magnitude), then grows by kt times the tangential relative displacement;
      the trial force is capped at mu f_n (Coulomb); out of contact the history is reset;
      Hertz-Mindlin (``warp_hcell.dem.laws.hertz_mindlin``): f_n = kh delta^(3/2), mean
      Mindlin stiffness in place of kt;
    - contact when the gap is <= contact_tolerance (r_i + r_j); a gap >= 0 carries zero force;
    - free DOFs, driven DOFs, relaxation, adaptive rate, prediction and refinement exactly as
      in the 2D kernel;
    - cell volume: the polyhedron of the outer faces (triangles of grain centres, oriented
      outwards), V = abs(sum_f x_a . (x_b x x_c)) / 6.
"""

import functools

import warp as wp

from warp_hcell.dem.laws import warp_law
from warp_hcell.dem.pairs import pair_loops
from warp_hcell.dem.stepping import cell_step_kernel, grain_matrix, mask_code
from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

DIM = 3
"""Spatial dimension of the cells this module steps."""


@wp.func
def spatial_pair_force(u: wp.vec3d, normal: wp.float64, spring: wp.vec3d):
    """The force on grain i by grain j [N]: -f_n u + f_s."""
    return spring - normal * u


@functools.lru_cache(maxsize=None)
def pair_pieces_3d(pairs: tuple[tuple[int, int], ...], n_grains: int,
                   law: str = "linear") -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``setup``, ``forces``, ``output``) of the spatial pairs (i, j) of one topology with contact law
    ``law`` (``warp_hcell.dem.pairs.pair_loops``); a pair's spring is a vector (a row of an (n_pairs, 3) matrix)."""
    return pair_loops(pairs, n_grains, DIM, warp_law(law).spatial_contact, spatial_pair_force, law)


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
                   faces: tuple[tuple[int, int, int], ...], law: str = "linear") -> wp.Kernel:
    """The 3D cell-step kernel for one topology and contact law.

    Args:
        pairs: candidate contact pairs (i, j), 0-based, i < j.
        driven: per grain, driven along (n, t1, t2).
        faces: outer triangles (a, b, c) of grain indices, oriented outwards (volume V_cell).
        law: contact-law name (``warp_hcell.dem.laws``).

    Returns:
        A kernel launched with one thread per cell of cells [first_cell, first_cell + dim).
    """
    drive = tuple(tuple(bool(v) for v in d) for d in driven)
    n_grains = len(drive)
    return cell_step_kernel(drive, len(pairs), pair_pieces_3d(pairs, n_grains, law), polyhedron_volume(faces, n_grains),
                            8192)
