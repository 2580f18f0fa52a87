"""Central finite differences of a cell model's step with respect to its own increment.

The reference against which every backend's consistent tangent is checked:
``warp_hcell.core.checks.central_difference_tangent`` uses nothing of the backend but ``step``
itself; ``fd_tangent_fixed_schedule`` (DEM cells) also holds the DEM's driving schedule over
the stencil.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np


def relative_error(tangent: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per cell: max |tangent - reference| / max |reference| [-], shape (n_cells,)."""
    scale = np.abs(reference).max(axis=(1, 2))
    return np.abs(tangent - reference).max(axis=(1, 2)) / scale


def fd_tangent_fixed_schedule(model, state, d_eps: np.ndarray, h: float) -> np.ndarray:
    """Central differences of a DEM cell's step with its driving schedule held over the stencil.

    The DEM drives the cell at ``rate`` = strain per substep along its largest strain
    component, s_k = k rate / max |d_eps| for k < n = ceil(max |d_eps| / rate), the last substep
    shorter (``warp_hcell.dem.kernels``). A difference step along the largest component changes
    that last substep by h itself, and the relaxation that follows it ends in a slightly
    different sliding state: the step's slope along that component differs from the
    quasi-static one by 0.25 to 2.6 % in slide, at any rate (docs/bvp.md, section 1). Here every
    stencil point is stepped at rate * max |d_eps + dh| / max |d_eps| (strain_per_substep and
    refined_strain_per_substep both), so that the substep fractions s_k are those of
    ``d_eps`` itself: the difference quotient is the slope of the step along one fixed
    discretised path, the quantity the condensed tangent describes.

    Requires both rates of the model's settings to be equal (no adaptive rate decision), and
    no tie of the largest |d_eps| component with another within the stencil (a kink of max |d_eps|).

    Args:
        model: a ``warp_hcell.dem.cell.DemCell``.
        state: cells at the start of the increment (``DemCellState``).
        d_eps: the increment [-], shape (n_cells, dim).
        h: difference step [-].

    Returns:
        Shape (n_cells, dim, dim): [:, a, b] = d S_aa / d d_eps_b [N m].
    """
    settings = state.model.settings
    if settings.refined_strain_per_substep != settings.strain_per_substep:
        raise ValueError("fd_tangent_fixed_schedule needs refined_strain_per_substep == strain_per_substep")
    d_eps = np.asarray(d_eps, dtype=np.float64)
    dim = d_eps.shape[1]
    diagonal = np.arange(dim)
    magnitude = np.sort(np.abs(d_eps), axis=1)
    if np.any(magnitude[:, -1] - magnitude[:, -2] <= 2.0 * h):
        raise ValueError("the largest |d_eps| component ties with another within the difference stencil")
    largest = magnitude[:, -1]
    out = np.empty((d_eps.shape[0], dim, dim))
    for b in range(dim):
        moments = []
        for sign in (1.0, -1.0):
            point = d_eps.copy()
            point[:, b] += sign * h
            stretch = np.abs(point).max(axis=1) / largest
            moment = np.empty((d_eps.shape[0], dim))
            for factor in np.unique(stretch):
                cells = np.flatnonzero(stretch == factor)
                rate = settings.strain_per_substep * factor
                group = model.take(state, cells)
                held = replace(group.model, settings=replace(settings, strain_per_substep=rate,
                                                              refined_strain_per_substep=rate))
                moment[cells] = model.step(replace(group, model=held), point[cells])[1].moment[:, diagonal, diagonal]
            moments.append(moment)
        out[:, :, b] = (moments[0] - moments[1]) / (2.0 * h)
    return out
