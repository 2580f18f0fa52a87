"""Warp code of the planar meso-DEM: the batched cell-step kernel (float64); the contact law is
``warp_hcell.dem.contact``.

One thread advances one cell through a whole strain increment: the substep loop runs
inside the kernel and the cell (positions, velocities, displacements, shear forces) lives in
fixed-size local matrices; the pieces shared with the 3D kernel are ``warp_hcell.dem.stepping``
and the pair loops ``warp_hcell.dem.pairs``; the law of one planar pair and the cell area are
below. Kernels are generated per topology (candidate pairs and driven DOF mask are
compile-time constants), so every grain/pair index is static and the loops are unrolled;
``step_kernel`` caches one kernel per topology. Measured on the H-cell (CPU, one thread, 1e5
cells): 1.9e7 cell-substeps per CPU-second, 1.8 times the same kernel reading the pair and
driven tables from arrays in rolled loops (bit-identical results).

Conventions inside the kernels (tension-positive DEM quantities, local frame (n, t)):
    - pair p = (i, j): unit normal ``u = (x_j - x_i) / |x_j - x_i|``, tangent w = (-u_t, u_n);
    - ``contact_force[p]`` is the force exerted ON grain i BY grain j: -f_n u + f_s w,
      with f_n >= 0 the normal (repulsive) force and f_s the tangential spring force
      (``shear_force``), which grows by kt * ((dx_j - dx_i) . w);
    - a pair is in contact when its gap is <= contact_tolerance * (r_i + r_j); a contact with
      a gap >= 0 carries zero force (and so zero shear force); out of contact the shear
      history is reset;
    - free DOFs: explicit (leapfrog) integration with Cundall local damping
      (``warp_hcell.dem.stepping.damped_velocity``), from rest at the start of each increment; a free grain whose net
      force is exactly zero is set at rest (no drift of unloaded grains in mechanism states);
    - driven DOFs: x = x_ref * l(s) / l_ref with l(s) moving linearly from the old to the new
      cell size, s = min(k rate / max abs(d_eps), 1) over n = ceil(max abs(d_eps) / rate) driving
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
      opens, closes, starts or stops sliding, the rest is driven at refined_strain_per_substep;
      once a contact closes, at closing_strain_per_substep, and the next increment grows its rate
      from there with the free grains unpredicted (docs/dem_stepping.md, "Contacts that close
      again").

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
