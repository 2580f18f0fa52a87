"""The pieces of the cell-step kernels that hold in any dimension (Warp, float64).

The planar (``warp_hcell.dem.kernels``) and spatial (``warp_hcell.dem.kernels3d``) kernels
hold a cell in fixed-size local matrices, one row a grain, one column an axis ((n, t) or
(n, t1, t2)), and step it with the functions below, each with one job: the driving path of
the increment, the adaptive rate with the prediction of the free grains, the refinement on a
regime change, the convergence measure, the leapfrog move and the velocity memory (the
conventions are in ``warp_hcell.dem.kernels``; the pair loops are ``warp_hcell.dem.pairs``).
Functions return new local matrices; none changes its arguments.

What depends on which DOFs are driven is generated per mask ``drive`` (per grain, per axis,
True where driven), loops unrolled. Each generated function carries its mask as a static
constant (``mask_code``): Warp hashes the static expressions that depend on a loop variable
only when it generates the code, so without it two masks of the same size would share one
compiled module.
"""

import functools

import warp as wp

from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@functools.lru_cache(maxsize=None)
def grain_matrix(n_grains: int, dim: int) -> type:
    """The local matrix type of a cell's grains, shape (n_grains, dim), float64."""
    return wp.types.matrix(shape=(n_grains, dim), dtype=wp.float64)


@functools.lru_cache(maxsize=None)
def grain_vector(n_grains: int) -> type:
    """The local vector type of one value per grain, float64."""
    return wp.types.vector(length=n_grains, dtype=wp.float64)


def cell_vector(dim: int) -> type:
    """The vector type of a cell size or strain increment: ``wp.vec2d`` or ``wp.vec3d``."""
    return wp.vec2d if dim == 2 else wp.vec3d


def spring_types(n_pairs: int, dim: int) -> tuple[type, type]:
    """(the local type of a cell's tangential springs, the type of one pair's spring): an
    (n_pairs,) vector and float64 in the plane, an (n_pairs, 3) matrix and ``wp.vec3d`` in space."""
    if dim == 2:
        return wp.types.vector(length=n_pairs, dtype=wp.float64), wp.float64
    return grain_matrix(n_pairs, dim), cell_vector(dim)


def mask_code(*tables: tuple[tuple[int, ...], ...]):
    """Tables of ints (a drive mask, candidate pairs) as one Warp int32 vector constant, their sizes first."""
    flat = [len(t) for t in tables] + [int(v) for t in tables for row in t for v in row]
    return wp.types.vector(length=len(flat), dtype=wp.int32)(*flat)


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


@wp.func
def refined_schedule(changed: wp.int32, closed: wp.int32, refined: wp.int32, s: wp.float64, s_base: wp.float64,
                     ds: wp.float64, n_phase: wp.int32, k_phase: wp.int32, largest: wp.float64,
                     refined_strain_per_substep: wp.float64, closing_strain_per_substep: wp.float64):
    """The driving schedule after a substep: once a contact has opened, closed, started or stopped
    sliding (``changed`` = 1), the rest of the increment is driven at refined_strain_per_substep;
    once a contact has closed (``closed`` = 1), at closing_strain_per_substep. ``refined`` is the
    level reached: 0 none, 1 refined, 2 closing.

    A contact closes with no force and its spring at zero, and the free grains it touches are
    at rest: while they lag behind the driving, a closing contact whose quasi-static state
    sticks near the Coulomb cap (a wedge near alpha = 90 deg - phi_g) slides and loses spring
    it never regains. The slip grows with the strain per substep (docs/dem_stepping.md).

    Returns:
        (refined, s_base, ds, n_phase, k_phase): s = s_base + k_phase ds over n_phase substeps.
    """
    level = wp.where(closed == 1, wp.int32(2), wp.where(changed == 1, wp.int32(1), wp.int32(0)))
    if level > refined:
        refined = level
        rate = wp.where(level == 2, closing_strain_per_substep, refined_strain_per_substep)
        n_rest = wp.int32(wp.ceil((wp.float64(1.0) - s) * largest / rate))
        if n_rest > n_phase - k_phase:
            s_base = s
            ds = rate / largest
            n_phase = n_rest
            k_phase = wp.int32(0)
    return refined, s_base, ds, n_phase, k_phase


@functools.lru_cache(maxsize=None)
def driving_path(dim: int) -> wp.Function:
    """``path(l_start, l_ref, d_eps)``: the cell's sizes over the increment, l(s) = l_start + (l_end - l_start) s.

    Returns (l_end [m], largest = max abs(d_eps) [-], x/x_ref at s = 0 and its change over the increment).
    """
    vec = cell_vector(dim)

    @wp.func
    def path(l_start: vec, l_ref: vec, de: vec):
        one = wp.float64(1.0)
        l_end = vec()
        scale0 = vec()
        dscale = vec()
        largest = wp.abs(de[0])
        for a in range(wp.static(dim)):
            l_end[a] = l_start[a] * (one - de[a])
            if wp.static(a > 0):
                largest = wp.max(largest, wp.abs(de[a]))
        for a in range(wp.static(dim)):
            scale0[a] = l_start[a] / l_ref[a]
            dscale[a] = (l_end[a] - l_start[a]) / l_ref[a]
        return l_end, largest, scale0, dscale

    return path


@functools.lru_cache(maxsize=None)
def rate_and_prediction(drive: tuple[tuple[bool, ...], ...]) -> wp.Function:
    """``predict(v, ref, dscale, h, largest, ...)``: the strain per substep and the free grains' drift.

    From the cell's own state (v: each grain's mean velocity over the last increment's driving
    substeps): for the driven DOFs d_last = v h is the last driving rate per substep, d_new = D_new / n
    this increment's at the coarse rate, lam = (d_last . d_new) / (d_new . d_new). The increment
    continues the last one when max abs(d_last - lam d_new) <= velocity_change lam max abs(d_new);
    then the rate may grow by rate_growth up to strain_per_substep (else refined_strain_per_substep;
    after closing_strain_per_substep it grows from there), and the free grains drift by span v_last,
    span = (v_last . D_new) / (v_last . v_last) [s] over the driven DOFs.

    Returns (velocities with the free DOFs at rest, drift [m/s], driving substeps, ds)."""
    n_grains, dim = len(drive), len(drive[0])
    mat = grain_matrix(n_grains, dim)
    vec = cell_vector(dim)
    code = mask_code(drive)

    @wp.func
    def predict(v: mat, ref: mat, dscale: vec, h: wp.float64, largest: wp.float64, strain_per_substep: wp.float64,
                refined_strain_per_substep: wp.float64, closing_strain_per_substep: wp.float64,
                velocity_change: wp.float64, rate_growth: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        inv_n_coarse = one / wp.float64(wp.max(wp.int32(wp.ceil(largest / strain_per_substep)), 1))
        dot = zero
        norm2 = zero
        dot_v = zero
        norm_v = zero
        d_new = mat()
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(dim)):
                if wp.static(drive[g][a]):
                    d_new[g, a] = ref[g, a] * dscale[a] * inv_n_coarse
                    dot = dot + v[g, a] * h * d_new[g, a]
                    norm2 = norm2 + d_new[g, a] * d_new[g, a]
                    dot_v = dot_v + v[g, a] * (ref[g, a] * dscale[a])
                    norm_v = norm_v + v[g, a] * v[g, a]
        lam = wp.where(norm2 > zero, dot / wp.where(norm2 > zero, norm2, one), zero)
        off = zero
        driving_size = zero
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(dim)):
                if wp.static(drive[g][a]):
                    off = wp.max(off, wp.abs(v[g, a] * h - lam * d_new[g, a]))
                    driving_size = wp.max(driving_size, wp.abs(d_new[g, a]))
        steady = lam > zero and off <= velocity_change * lam * driving_size
        rate = refined_strain_per_substep
        if steady:
            rate = wp.min(strain_per_substep, wp.max(closing_strain_per_substep, rate_growth * lam * largest * inv_n_coarse))
        n_phase = wp.int32(wp.ceil(largest / rate))
        ds = wp.where(largest > zero, rate / wp.where(largest > zero, largest, one), zero)
        span = wp.where(steady and norm_v > zero, dot_v / wp.where(norm_v > zero, norm_v, one), zero)
        rest = mat()
        drift = mat()
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(dim)):
                if wp.static(drive[g][a]):
                    rest[g, a] = v[g, a]
                else:
                    drift[g, a] = span * v[g, a]
        return rest, drift, n_phase, ds

    return predict


@functools.lru_cache(maxsize=None)
def grain_motion(drive: tuple[tuple[bool, ...], ...]) -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``unbalanced(f)``, ``move(...)``, ``memory(...)``) of the mask ``drive``.

    - ``unbalanced(f)``: the largest net force on a free DOF [N];
    - ``move(x, v, f, drift, ref, scale0, dscale, s, s_prev, inv_mass, h, damping)``: one
      substep, (x, v, dx): driven DOFs to x_ref (scale0 + dscale s), free ones by leapfrog with
      Cundall damping plus the drift over (s - s_prev); a free grain whose net force is exactly
      zero is held at rest;
    - ``memory(x, x0, ref, dscale, driving, h, closed, ds)``: every DOF's mean velocity over the
      increment's driving substeps (driven: the driving rate; free: how it moved while the cell
      was driven), zero without driving. Where a contact closed in the increment (``closed`` = 1)
      the driven DOFs keep the rate of the last driving substep (ds, a fraction of the increment)
      and the free DOFs' memory is zero: they moved in another contact state
      (docs/dem_stepping.md)."""
    n_grains, dim = len(drive), len(drive[0])
    mat = grain_matrix(n_grains, dim)
    vec = cell_vector(dim)
    vec_g = grain_vector(n_grains)
    code = mask_code(drive)

    @wp.func
    def unbalanced(f: mat):
        wp.static(code)
        largest = wp.float64(0.0)
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(dim)):
                if wp.static(not drive[g][a]):
                    largest = wp.where(wp.abs(f[g, a]) > largest, wp.abs(f[g, a]), largest)
        return largest

    @wp.func
    def move(x: mat, v: mat, f: mat, drift: mat, ref: mat, scale0: vec, dscale: vec, s: wp.float64,
             s_prev: wp.float64, inv_mass: vec_g, h: wp.float64, damping: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        x_new = mat()
        v_new = mat()
        dx = mat()
        for g in range(wp.static(n_grains)):
            unloaded = f[g, 0] == zero
            for a in range(wp.static(dim)):
                if wp.static(a > 0):
                    unloaded = unloaded and f[g, a] == zero
            for a in range(wp.static(dim)):
                if wp.static(drive[g][a]):
                    x_new[g, a] = ref[g, a] * (scale0[a] + dscale[a] * s)
                    dx[g, a] = x_new[g, a] - x[g, a]
                    v_new[g, a] = v[g, a]
                else:
                    vel = wp.where(unloaded, zero, damped_velocity(f[g, a], v[g, a], inv_mass[g], h, damping))
                    v_new[g, a] = vel
                    step = vel * h + wp.where(unloaded, zero, drift[g, a] * (s - s_prev))
                    dx[g, a] = step
                    x_new[g, a] = x[g, a] + step
        return x_new, v_new, dx

    @wp.func
    def memory(x: mat, x0: mat, ref: mat, dscale: vec, driving: wp.int32, h: wp.float64, closed: wp.int32,
               ds: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        v = mat()
        for g in range(wp.static(n_grains)):
            for a in range(wp.static(dim)):
                if wp.static(drive[g][a]):
                    v[g, a] = wp.where(driving > 0,
                                       wp.where(closed == 0, ref[g, a] * dscale[a] / (wp.float64(driving) * h),
                                                ref[g, a] * dscale[a] * ds / h), zero)
                else:
                    v[g, a] = wp.where(driving > 0 and closed == 0,
                                       (x[g, a] - x0[g, a]) / (wp.float64(wp.max(driving, 1)) * h), zero)
        return v

    return unbalanced, move, memory


@functools.lru_cache(maxsize=None)
def grain_io(n_grains: int, dim: int) -> tuple[wp.Function, wp.Function]:
    """(``load(position, velocity, reference_position, inv_mass, c)``, ``store(rows, out, c)``):
    a cell's per-grain arrays into local matrices (x, v, x_ref, 1/m) and one matrix back out."""
    mat = grain_matrix(n_grains, dim)
    vec = cell_vector(dim)
    vec_g = grain_vector(n_grains)

    @wp.func
    def load(position: wp.array2d(dtype=vec), velocity: wp.array2d(dtype=vec),
             reference_position: wp.array2d(dtype=vec), inv_mass: wp.array2d(dtype=wp.float64), c: wp.int32):
        x = mat()
        v = mat()
        ref = mat()
        im = vec_g()
        for g in range(wp.static(n_grains)):
            p0 = position[c, g]
            q0 = velocity[c, g]
            r0 = reference_position[c, g]
            for a in range(wp.static(dim)):
                x[g, a] = p0[a]
                v[g, a] = q0[a]
                ref[g, a] = r0[a]
            im[g] = inv_mass[c, g]
        return x, v, ref, im

    @wp.func
    def store(rows: mat, out: wp.array2d(dtype=vec), c: wp.int32):
        for g in range(wp.static(n_grains)):
            row = vec()
            for a in range(wp.static(dim)):
                row[a] = rows[g, a]
            out[c, g] = row

    return load, store


def cell_step_kernel(drive: tuple[tuple[bool, ...], ...], n_pairs: int,
                     pairs: tuple[wp.Function, wp.Function, wp.Function], measure: wp.Function,
                     max_unroll: int) -> wp.Kernel:
    """The cell-step kernel of one topology, in the plane or in space (``len(drive[0])``).

    Args:
        drive: per grain, per axis, True where driven.
        n_pairs: number of candidate pairs.
        pairs: the pair functions (``setup``, ``forces``, ``output``) of ``warp_hcell.dem.pairs.pair_pieces``
            with the dimension's law of one pair (``warp_hcell.dem.kernels.pair_pieces``,
            ``warp_hcell.dem.kernels3d.pair_pieces_3d``).
        measure: V_cell of the grain centres (the outer polygon's area, the polyhedron's volume).
        max_unroll: Warp's limit of unrolled loop iterations for this kernel.

    Returns:
        A kernel launched with one thread per cell of cells [first_cell, first_cell + dim)
        (``warp_hcell.dem.integrator.launch_step``: the argument order).
    """
    n_grains, dim = len(drive), len(drive[0])
    vec = cell_vector(dim)
    moment_type = wp.mat22d if dim == 2 else wp.mat33d
    shear_type = spring_types(n_pairs, dim)[1]
    load, store = grain_io(n_grains, dim)
    setup, forces, output = pairs
    path = driving_path(dim)
    predict = rate_and_prediction(drive)
    unbalanced, move, memory = grain_motion(drive)
    mat_g = grain_matrix(n_grains, dim)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)

    @wp.kernel(module="unique", module_options={**MODULE_OPTIONS, "max_unroll": max_unroll})
    def dem_step(
        radius: wp.array2d(dtype=wp.float64), inv_mass: wp.array2d(dtype=wp.float64),
        reference_position: wp.array2d(dtype=vec), reference_cell_size: wp.array(dtype=vec),
        dt: wp.array(dtype=wp.float64), force_floor: wp.array(dtype=wp.float64),
        kn: wp.float64, kt: wp.float64, mu: wp.float64, damping: wp.float64, contact_tolerance: wp.float64,
        strain_per_substep: wp.float64, refined_strain_per_substep: wp.float64,
        closing_strain_per_substep: wp.float64, velocity_change: wp.float64,
        rate_growth: wp.float64, force_tolerance: wp.float64, max_substeps: wp.int32,
        position_in: wp.array2d(dtype=vec), velocity_in: wp.array2d(dtype=vec),
        shear_force_in: wp.array2d(dtype=shear_type), cell_size_in: wp.array(dtype=vec),
        d_eps_local: wp.array(dtype=vec), first_cell: wp.int32,
        # outputs
        position_out: wp.array2d(dtype=vec), velocity_out: wp.array2d(dtype=vec),
        shear_force_out: wp.array2d(dtype=shear_type), contact_force_out: wp.array2d(dtype=vec),
        contact_out: wp.array2d(dtype=wp.int32), cell_size_out: wp.array(dtype=vec),
        moment_out: wp.array(dtype=moment_type), measure_out: wp.array(dtype=wp.float64),
        substeps_out: wp.array(dtype=wp.int32), converged_out: wp.array(dtype=wp.int32),
    ):
        c = first_cell + wp.tid()
        h = dt[c]
        floor = force_floor[c]
        x, v, ref, im = load(position_in, velocity_in, reference_position, inv_mass, c)
        x0 = x
        dx = mat_g()
        fs, rsum, cut2, scale = setup(radius, shear_force_in, c, contact_tolerance)
        was_regime = vec_p()
        l_end, largest, scale0, dscale = path(cell_size_in[c], reference_cell_size[c], d_eps_local[c])
        v, drift, n_phase, ds = predict(v, ref, dscale, h, largest, strain_per_substep, refined_strain_per_substep,
                                        closing_strain_per_substep, velocity_change, rate_growth)
        s_base = wp.float64(0.0)
        s = wp.float64(0.0)
        s_prev = wp.float64(0.0)
        k_phase = wp.int32(0)
        refined = wp.int32(0)
        substeps = wp.int32(0)
        driving = wp.int32(0)
        converged = wp.int32(0)
        closures = wp.int32(0)
        while True:
            f, fs, was_regime, fmax, changed, closed = forces(x, dx, fs, rsum, cut2, scale, was_regime, substeps, kn, kt,
                                                                        mu)
            closures = wp.max(closures, closed)
            if k_phase < n_phase:
                refined, s_base, ds, n_phase, k_phase = refined_schedule(changed, closed, refined, s, s_base, ds,
                                                                         n_phase, k_phase, largest,
                                                                         refined_strain_per_substep,
                                                                         closing_strain_per_substep)
            else:
                if unbalanced(f) <= force_tolerance * wp.where(fmax > floor, fmax, floor):
                    converged = 1
                    break
                if substeps >= max_substeps:
                    break
            substeps += 1
            s_prev = s
            if k_phase < n_phase:
                k_phase += 1
                driving += 1
                s = wp.where(k_phase < n_phase, wp.min(s_base + wp.float64(k_phase) * ds, wp.float64(1.0)),
                             wp.float64(1.0))
            x, v, dx = move(x, v, f, drift, ref, scale0, dscale, s, s_prev, im, h, damping)
        store(x, position_out, c)
        store(memory(x, x0, ref, dscale, driving, h, closures, ds), velocity_out, c)
        moment_out[c] = output(x, fs, rsum, cut2, scale, kn, shear_force_out, contact_force_out, contact_out, c)
        measure_out[c] = measure(x)
        cell_size_out[c] = l_end
        substeps_out[c] = substeps
        converged_out[c] = converged

    return dem_step
