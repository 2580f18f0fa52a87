"""Warp code of the planar meso-DEM: the batched cell-step kernel (float64); the contact law is
``warp_hcell.dem.contact``.

One thread advances one cell through a whole strain increment: the substep loop runs
inside the kernel and the cell (positions, velocities, displacements, shear forces) lives in
fixed-size local matrices; the pieces shared with the 3D kernel are ``warp_hcell.dem.stepping``,
the pair pieces of the plane are below. Kernels are generated per topology (candidate pairs and driven
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
      opens, closes, starts or stops sliding, the rest is driven at refined_strain_per_substep.

The conversion to compression-positive quantities happens on the host
(``warp_hcell.database.learning_state.to_compression_positive``).
"""

import functools

import warp as wp

from warp_hcell.dem.contact import contact_law, contact_regime, normal_force
from warp_hcell.dem.stepping import cell_step_kernel, grain_matrix, mask_code, pair_setup

wp.set_module_options({"enable_backward": False})


@functools.lru_cache(maxsize=None)
def pair_pieces(pairs: tuple[tuple[int, int], ...], n_grains: int) -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``setup``, ``forces``, ``output``): the planar pairs (i, j) of one topology.

    - ``setup``: ``warp_hcell.dem.stepping.pair_setup``;
    - ``forces(x, dx, fs, rsum, cut2, was_regime, substeps, kn, kt, mu)``: the contact forces at
      the grain centres x with the shear increment from the last move dx: (net force per grain,
      new f_s, regime per pair (0 open, 1 sticking, 2 sliding), largest normal force, 1 if a
      regime changed since the last evaluation);
    - ``output(x, fs, rsum, cut2, kn, shear_force_out, contact_force_out, contact_out, c)``: writes
      the pairs' state and forces (the last force evaluation ran at these positions: same
      contacts, same normal forces) and returns the Love-Weber sum (tension positive)
      sum_p f_p (x) (x_j - x_i).
    """
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    mat = grain_matrix(n_grains, 2)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)
    code = mask_code(pairs)

    setup = pair_setup(pairs, 2)

    @wp.func
    def forces(x: mat, dx: mat, fs: vec_p, rsum: vec_p, cut2: vec_p, was_regime: vec_p, substeps: wp.int32,
               kn: wp.float64, kt: wp.float64, mu: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        f = mat()
        shear_new = vec_p()
        regime_new = vec_p()
        fmax = zero
        changed = wp.int32(0)
        for p in range(wp.static(n_pairs)):
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            bn = x[j, 0] - x[i, 0]
            bt = x[j, 1] - x[i, 1]
            dist2 = bn * bn + bt * bt
            regime = zero
            shear = zero
            if dist2 <= cut2[p]:
                dist = wp.sqrt(dist2)
                inv_dist = one / dist
                un = bn * inv_dist
                ut = bt * inv_dist
                du = (dx[j, 1] - dx[i, 1]) * un - (dx[j, 0] - dx[i, 0]) * ut
                normal, shear = contact_law(rsum[p] - dist, du, fs[p], kn, kt, mu)
                regime = contact_regime(normal, wp.abs(shear), mu * normal)
                fin = -normal * un - shear * ut
                fit = -normal * ut + shear * un
                f[i, 0] = f[i, 0] + fin
                f[i, 1] = f[i, 1] + fit
                f[j, 0] = f[j, 0] - fin
                f[j, 1] = f[j, 1] - fit
                fmax = wp.where(normal > fmax, normal, fmax)
            shear_new[p] = shear
            changed = wp.where(substeps > 0 and regime != was_regime[p], 1, changed)
            regime_new[p] = regime
        return f, shear_new, regime_new, fmax, changed

    @wp.func
    def output(x: mat, fs: vec_p, rsum: vec_p, cut2: vec_p, kn: wp.float64,
               shear_force_out: wp.array2d(dtype=wp.float64), contact_force_out: wp.array2d(dtype=wp.vec2d),
               contact_out: wp.array2d(dtype=wp.int32), c: wp.int32):
        wp.static(code)
        zero = wp.float64(0.0)
        m_nn = zero
        m_nt = zero
        m_tn = zero
        m_tt = zero
        for p in range(wp.static(n_pairs)):
            shear_force_out[c, p] = fs[p]
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            bn = x[j, 0] - x[i, 0]
            bt = x[j, 1] - x[i, 1]
            dist2 = bn * bn + bt * bt
            dist = wp.sqrt(dist2)
            un = bn / dist
            ut = bt / dist
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
        return wp.mat22d(m_nn, m_nt, m_tn, m_tt)

    return setup, forces, output


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
