"""Warp code of the planar meso-DEM: the batched cell-step kernel (float64); the contact law is
``warp_hcell.dem.contact``.

One thread advances one cell through a whole strain increment: the substep loop runs inside the
kernel and the cell (positions, velocities, displacements, shear forces) lives in fixed-size
local matrices. The stepping shared with the 3D kernel is ``warp_hcell.dem.stepping``, the pair
loops ``warp_hcell.dem.pairs``; the law of one planar pair and the cell area are below. Kernels
are generated per topology (candidate pairs and driven DOF mask are compile-time constants, loops
unrolled); ``step_kernel`` caches one kernel per topology. Throughput: docs/studies/bench_dem_kernel.md.

Conventions inside the kernels (tension-positive DEM quantities, local frame (n, t)):
    - pair p = (i, j): unit normal ``u = (x_j - x_i) / |x_j - x_i|``, tangent w = (-u_t, u_n);
    - ``contact_force[p]`` is the force ON grain i BY grain j: -f_n u + f_s w, f_n >= 0 the
      normal (repulsive) force, f_s the tangential spring force (``shear_force``), which grows
      by kt * ((dx_j - dx_i) . w);
    - contact when the gap is <= contact_tolerance * (r_i + r_j); a contact with a gap >= 0
      carries zero force; out of contact the shear history is reset;
    - free DOFs: leapfrog with Cundall local damping (``stepping.damped_velocity``), from rest
      at the start of each increment; a free grain with exactly zero net force is held at rest;
    - driven DOFs: x = x_ref * l(s) / l_ref, l(s) linear from the old to the new cell size over
      n = ceil(max abs(d_eps) / rate) driving substeps; then relaxation until max free-DOF force
      <= force_tolerance * max(max normal force, force_floor), or max_substeps;
    - adaptive rate, prediction of the free grains and refinement on a regime change from the
      cell's own state (``warp_hcell.dem.stepping``, docs/dem_stepping.md).

The conversion to compression-positive quantities happens on the host
(``warp_hcell.database.learning_state.to_compression_positive``).
"""

import functools

import warp as wp

from warp_hcell.dem.contact import contact_law, contact_regime
from warp_hcell.dem.pairs import pair_loops
from warp_hcell.dem.stepping import cell_step_kernel, grain_matrix, mask_code
from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@wp.func
def planar_contact(u: wp.vec2d, rel: wp.vec2d, overlap: wp.float64, spring: wp.float64, kn: wp.float64,
                   kt: wp.float64, mu: wp.float64):
    """One planar pair within reach (``warp_hcell.dem.pairs``): the spring f_s grows by kt times
    du = rel . w, w = (-u_t, u_n); returns (f_n [N], new f_s [N], regime: 1 sticking, 2 sliding)."""
    du = rel[1] * u[0] - rel[0] * u[1]
    normal, shear = contact_law(overlap, du, spring, kn, kt, mu)
    return normal, shear, contact_regime(normal, wp.abs(shear), mu * normal)


@wp.func
def planar_pair_force(u: wp.vec2d, normal: wp.float64, spring: wp.float64):
    """The force on grain i by grain j [N]: -f_n u + f_s w, w = (-u_t, u_n)."""
    return wp.vec2d(-normal * u[0] - spring * u[1], -normal * u[1] + spring * u[0])


@functools.lru_cache(maxsize=None)
def pair_pieces(pairs: tuple[tuple[int, int], ...], n_grains: int) -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``setup``, ``forces``, ``output``) of the planar pairs (i, j) of one topology
    (``warp_hcell.dem.pairs.pair_loops``); a pair's spring is one value, f_s."""
    return pair_loops(pairs, n_grains, 2, planar_contact, planar_pair_force)


@functools.lru_cache(maxsize=None)
def polygon_area(outer: tuple[int, ...], n_grains: int) -> wp.Function:
    """``area(x)``: V_cell [m^2], the shoelace formula over the outer polygon of grain centres."""
    n_outer = len(outer)
    outer_next = tuple(outer[(k + 1) % n_outer] for k in range(n_outer))
    mat = grain_matrix(n_grains, 2)
    code = mask_code((outer,))

    @wp.func
    def area(x: mat):
        wp.static(code)
        twice_area = wp.float64(0.0)
        for k in range(wp.static(n_outer)):
            a = wp.static(outer[k])
            b = wp.static(outer_next[k])
            twice_area = twice_area + (x[a, 0] * x[b, 1] - x[b, 0] * x[a, 1])
        return wp.float64(0.5) * wp.abs(twice_area)

    return area


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
    drive = tuple(tuple(bool(v) for v in d) for d in driven)
    n_grains = len(drive)
    return cell_step_kernel(drive, len(pairs), pair_pieces(pairs, n_grains), polygon_area(outer, n_grains), 4096)
