"""The test of ``homogenization.ann.escalation.DemEscalation.released``, compiled (numba, float64, cells last).

Its own module, so that importing the escalation imports no numba until a hybrid takes the test.
"""

import math

import numba
import numpy as np


@numba.njit(cache=True, error_model="numpy")
def find_released(size, before, after, reference_position, reference_size, free_dofs, pairs, rsum, cut2, kn, ratio, out,
                  dofs, every):
    """``homogenization.ann.escalation.DemEscalation.released`` of cells last: size (dim, n) [m], before and
    after (n_free, n) [m]; the schema's reference_position (n_grains, dim) and reference_size (dim,) [m],
    free_dofs (n_free, 2) and pairs (n_pairs, 2) int64, rsum and cut2 (n_pairs,) [m, m^2]; kn [N/m]; ratio [-].
    Writes out (n,) bool and dofs (n_free, n) bool, the free DOFs of the released grains; every (bool): every
    grain counts as moved (dofs: those of the grains nothing presses at ``after``)."""
    n = size.shape[1]
    n_grains, dim = reference_position.shape
    x = np.empty((n_grains, dim, n))
    for g in range(n_grains):
        for a in range(dim):
            for c in range(n):
                x[g, a, c] = reference_position[g, a] * (size[a, c] / reference_size[a])
    moved = np.full((n_grains, n), every, dtype=np.bool_)
    for k in range(free_dofs.shape[0]):
        g, a = free_dofs[k, 0], free_dofs[k, 1]
        for c in range(n):
            x[g, a, c] = after[k, c]
            moved[g, c] |= after[k, c] != before[k, c]
    normal = np.empty((pairs.shape[0], n))
    largest = np.zeros(n)
    for p in range(pairs.shape[0]):
        i, j = pairs[p, 0], pairs[p, 1]
        for c in range(n):
            b = x[j, 0, c] - x[i, 0, c]
            dist2 = b * b
            for a in range(1, dim):
                b = x[j, a, c] - x[i, a, c]
                dist2 = dist2 + b * b
            force = kn * max(rsum[p] - math.sqrt(dist2), 0.0) if dist2 <= cut2[p] else 0.0
            normal[p, c] = force
            largest[c] = max(largest[c], force)
    pressed = np.zeros((n_grains, n), dtype=np.bool_)
    for p in range(pairs.shape[0]):
        i, j = pairs[p, 0], pairs[p, 1]
        for c in range(n):
            if normal[p, c] > ratio * largest[c]:
                pressed[i, c] = True
                pressed[j, c] = True
    for c in range(n):
        out[c] = False
    for g in range(n_grains):
        for c in range(n):
            out[c] |= moved[g, c] and not pressed[g, c]
    for k in range(free_dofs.shape[0]):
        g = free_dofs[k, 0]
        for c in range(n):
            dofs[k, c] = moved[g, c] and not pressed[g, c]
