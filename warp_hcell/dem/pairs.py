"""The pair loops of the cell-step kernels in any dimension (Warp, float64).

A cell's candidate pairs (i, j) are stepped by three generated functions: ``setup`` reads the
springs and the contact reach before the increment, ``forces`` evaluates every pair at the
current grain centres, ``output`` writes the pairs' state and forces and returns the
Love-Weber sum. What is the plane's or space's own is one pair's law, given by the dimension's
kernel module (``warp_hcell.dem.kernels``, ``warp_hcell.dem.kernels3d``) as two ``@wp.func``:

- ``contact(u, rel, overlap, spring, kn, kt, mu)``: (normal force f_n >= 0 [N], new spring [N],
  regime: 1 sticking, 2 sliding) of a pair within reach, from its unit normal u = (x_j - x_i) /
  norm(x_j - x_i), the relative displacement rel = dx_j - dx_i of the last move [m], the overlap
  r_i + r_j - norm(x_j - x_i) [m] and the spring before it;
- ``pair_force(u, normal, spring)``: the force on grain i by grain j [N], -f_n u plus the
  spring's force in the tangent plane.

The contact law is a compile-time choice by name (``warp_hcell.dem.laws``): ``setup`` computes
each pair's factor (``pair_scale``), ``contact`` and the law's ``normal_force`` get the pair's
constants (``pair_constant`` of the kernel's kn and kt and the factor; the linear law's: kn and kt
as they are).

The springs are one value per pair in the plane (a (n_pairs,) vector), a row of an
(n_pairs, 3) matrix in space; ``fs[p]`` is pair p's in either. Conventions (tension positive,
contact within contact_tolerance (r_i + r_j), history reset out of contact) are those of
``warp_hcell.dem.kernels``.
"""

import functools

import warp as wp

from warp_hcell.dem.laws import warp_law
from warp_hcell.dem.stepping import cell_vector, grain_matrix, mask_code, spring_types
from warp_hcell.dem.warp_options import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)


@functools.lru_cache(maxsize=None)
def pair_setup(pairs: tuple[tuple[int, int], ...], dim: int, law: str = "linear") -> wp.Function:
    """``setup(radius, shear_force_in, c, contact_tolerance)``: a cell's pairs (i, j) before the
    increment: (tangential springs [N], r_i + r_j [m], squared reach ((r_i + r_j)(1 + tolerance))^2,
    per-pair factor of the law's constants (``warp_hcell.dem.laws``: ``pair_scale``))."""
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)
    springs, spring_in = spring_types(n_pairs, dim)
    code = mask_code(pairs)
    pair_scale = warp_law(law).pair_scale

    @wp.func
    def setup(radius: wp.array2d(dtype=wp.float64), shear_force_in: wp.array2d(dtype=spring_in), c: wp.int32,
              contact_tolerance: wp.float64):
        wp.static(code)
        fs = springs()
        rsum = vec_p()
        cut2 = vec_p()
        scale = vec_p()
        widen = wp.float64(1.0) + contact_tolerance
        for p in range(wp.static(n_pairs)):
            if wp.static(dim == 2):
                fs[p] = shear_force_in[c, p]
            else:
                s0 = shear_force_in[c, p]
                for a in range(wp.static(dim)):
                    fs[p, a] = s0[a]
            r_i = radius[c, wp.static(pi[p])]
            r_j = radius[c, wp.static(pj[p])]
            r_sum = r_i + r_j
            rsum[p] = r_sum
            cut2[p] = (r_sum * widen) * (r_sum * widen)
            scale[p] = pair_scale(r_i, r_j, r_sum)
        return fs, rsum, cut2, scale

    return setup


def pair_loops(pairs: tuple[tuple[int, int], ...], n_grains: int, dim: int, contact: wp.Function,
                pair_force: wp.Function, law: str = "linear") -> tuple[wp.Function, wp.Function, wp.Function]:
    """(``setup``, ``forces``, ``output``) of the pairs (i, j) of one topology, with the
    dimension's ``contact`` and ``pair_force`` (module docstring) of contact law ``law``.

    - ``setup``: ``pair_setup``;
    - ``forces(x, dx, fs, rsum, cut2, scale, was_regime, substeps, kn, kt, mu)``: the contact forces at
      the grain centres x with the shear increment from the last move dx: (net force per grain,
      new springs, regime per pair (0 open, 1 sticking, 2 sliding), largest normal force, 1 if a
      regime changed since the last evaluation, 1 if a pair came within reach since the last
      evaluation);
    - ``output(x, fs, rsum, cut2, scale, kn, shear_force_out, contact_force_out, contact_out, c)``: writes
      the pairs' state and forces (the last force evaluation ran at these positions: same
      contacts, same normal forces) and returns the Love-Weber sum (tension positive)
      sum_p f_p (x) (x_j - x_i), a (dim, dim) matrix.
    """
    n_pairs = len(pairs)
    pi = tuple(p[0] for p in pairs)
    pj = tuple(p[1] for p in pairs)
    mat = grain_matrix(n_grains, dim)
    vec = cell_vector(dim)
    vec_p = wp.types.vector(length=n_pairs, dtype=wp.float64)
    springs, spring_out = spring_types(n_pairs, dim)
    moment_type = wp.types.matrix(shape=(dim, dim), dtype=wp.float64)
    code = mask_code(pairs)
    law_functions = warp_law(law)
    pair_constant, law_normal_force = law_functions.pair_constant, law_functions.normal_force

    @wp.func
    def forces(x: mat, dx: mat, fs: springs, rsum: vec_p, cut2: vec_p, scale: vec_p, was_regime: vec_p,
               substeps: wp.int32, kn: wp.float64, kt: wp.float64, mu: wp.float64):
        wp.static(code)
        zero = wp.float64(0.0)
        f = mat()
        shear_new = springs()
        regime_new = vec_p()
        fmax = zero
        changed = wp.int32(0)
        closed = wp.int32(0)
        for p in range(wp.static(n_pairs)):
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            b = x[j] - x[i]
            dist2 = wp.dot(b, b)
            regime = zero
            if dist2 <= cut2[p]:
                dist = wp.sqrt(dist2)
                u = b * (wp.float64(1.0) / dist)
                normal, shear, regime = contact(u, dx[j] - dx[i], rsum[p] - dist, fs[p], pair_constant(kn, scale[p]),
                                                pair_constant(kt, scale[p]), mu)
                force = pair_force(u, normal, shear)
                shear_new[p] = shear
                for a in range(wp.static(dim)):
                    f[i, a] = f[i, a] + force[a]
                    f[j, a] = f[j, a] - force[a]
                fmax = wp.where(normal > fmax, normal, fmax)
            changed = wp.where(substeps > 0 and regime != was_regime[p], 1, changed)
            closed = wp.where(substeps > 0 and regime != zero and was_regime[p] == zero, 1, closed)
            regime_new[p] = regime
        return f, shear_new, regime_new, fmax, changed, closed

    @wp.func
    def output(x: mat, fs: springs, rsum: vec_p, cut2: vec_p, scale: vec_p, kn: wp.float64,
               shear_force_out: wp.array2d(dtype=spring_out), contact_force_out: wp.array2d(dtype=vec),
               contact_out: wp.array2d(dtype=wp.int32), c: wp.int32):
        wp.static(code)
        moment = moment_type()
        for p in range(wp.static(n_pairs)):
            i = wp.static(pi[p])
            j = wp.static(pj[p])
            shear = fs[p]
            shear_force_out[c, p] = shear
            b = x[j] - x[i]
            dist2 = wp.dot(b, b)
            dist = wp.sqrt(dist2)
            touching = dist2 <= cut2[p]
            normal = wp.where(touching, law_normal_force(rsum[p] - dist, pair_constant(kn, scale[p])),
                              wp.float64(0.0))
            force = pair_force(b / dist, normal, shear)
            contact_force_out[c, p] = force
            contact_out[c, p] = wp.where(touching, 1, 0)
            moment = moment + wp.outer(force, b)
        return moment

    return pair_setup(pairs, dim, law), forces, output
