"""``check_cell_model``: the cell contract checked on any backend, as scikit-learn's ``check_estimator``.

Run it on your own backend before using it in the homogenisation::

    from warp_hcell.core.checks import check_cell_model
    from warp_hcell.mesostructures.hcell import h_cell

    check_cell_model(MyCell(ContactLaw(), 0.5), h_cell(55.0))   # raises AssertionError on a breach

It builds a few cells of the mesostructure, compresses them isotropically so that their
contacts carry force, and checks, on mixed increments from there:

- the response: moment (n_cells, dim, dim) and area (n_cells,) finite, area > 0, S symmetric to
  ``symmetry_rtol`` of its largest entry and compressive on the diagonal (compression
  positive) after isotropic compression;
- purity: ``step`` leaves its input state (and increment) untouched, and the same input gives
  the same output, bit for bit;
- ``take`` and the array round trip: gathered and restored cells step exactly as the originals;
- batch invariance: a cell stepped alone gives, bit for bit, what it gives in its batch;
- the tangent (where ``step(..., with_tangent=True)`` returns one): against central
  differences of ``step`` itself, to ``tangent_rtol`` of its largest entry;
- the observables: one array of shape (n_cells,) per name.

Sign convention: compression and contraction positive.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from warp_hcell.core.contract import CellModel, CellResponse


def _arrays(model, state) -> dict[str, np.ndarray]:
    return {name: np.array(value) for name, value in model.state_to_arrays(state).items()}


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray], what: str) -> None:
    assert a.keys() == b.keys(), f"{what}: state arrays {sorted(a)} != {sorted(b)}"
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=f"{what}: state array {name!r}")


def central_difference_tangent(model, state, d_eps: np.ndarray, h: float) -> np.ndarray:
    """d(S_aa)/d(d_eps_b) [N m] by central differences of ``model.step``, (n_cells, dim, dim) for increments
    ``d_eps`` of shape (n_cells, dim) ((S_nn, S_tt) by (d_eps_n, d_eps_t) in 2D), difference step ``h`` [-]."""
    d_eps = np.asarray(d_eps, dtype=np.float64)
    dim = d_eps.shape[1]
    diagonal = np.arange(dim)
    out = np.empty((d_eps.shape[0], dim, dim))
    for b in range(dim):
        plus, minus = d_eps.copy(), d_eps.copy()
        plus[:, b] += h
        minus[:, b] -= h
        s_plus, s_minus = model.step(state, plus)[1].moment, model.step(state, minus)[1].moment
        out[:, :, b] = (s_plus[:, diagonal, diagonal] - s_minus[:, diagonal, diagonal]) / (2.0 * h)
    return out


def check_cell_model(model: Any, mesostructure: Any, *, n_cells: int = 4, precompression: float = 2e-3,
                     n_compression: int = 4, increment: float = 2e-5, seed: int = 0, symmetry_rtol: float = 1e-4,
                     fd_step: float = 1e-7, tangent_rtol: float = 0.05) -> None:
    """Check that ``model`` honours the cell contract on cells of ``mesostructure`` (module docstring).

    Args:
        model: the backend (a ``warp_hcell.core.contract.CellModel``).
        mesostructure: the cell every cell of the batch starts from.
        n_cells: cells of the batch.
        precompression: isotropic strain [-] applied first, in ``n_compression`` increments.
        increment: scale of the random mixed increments checked [-].
        seed: seed of those increments.
        symmetry_rtol: allowed asymmetry of S, relative to its largest entry [-].
        fd_step: step of the central differences [-].
        tangent_rtol: allowed tangent error, relative to its largest entry [-].

    Raises:
        AssertionError: naming the rule that failed.
    """
    assert isinstance(model, CellModel), f"{type(model).__name__} does not implement the CellModel protocol"
    dim = int(getattr(mesostructure, "dim", 2))
    state = model.init_state(mesostructure, n_cells)
    for _ in range(n_compression):
        state, _ = model.step(state, np.full((n_cells, dim), precompression / n_compression))
    d_eps = np.random.default_rng(seed).normal(scale=increment, size=(n_cells, dim))

    response = model.response(state)
    assert isinstance(response, CellResponse), "response() must return a CellResponse"
    assert response.moment.shape == (n_cells, dim, dim) and response.area.shape == (n_cells,), "response shapes"
    assert np.all(np.isfinite(response.moment)) and np.all(response.area > 0.0), "finite moment, positive area"
    scale = np.abs(response.moment).max()
    asymmetry = np.abs(response.moment - np.swapaxes(response.moment, 1, 2)).max()
    assert asymmetry <= symmetry_rtol * scale, "S symmetric"
    assert np.all(np.diagonal(response.moment, axis1=1, axis2=2) > 0.0), \
        "S compressive (positive) on the diagonal after isotropic compression"

    before, d_eps_copy = _arrays(model, state), d_eps.copy()
    first_state, first = model.step(state, d_eps)
    second_state, second = model.step(state, d_eps)
    _same(_arrays(model, state), before, "step must leave its input state untouched")
    np.testing.assert_array_equal(d_eps, d_eps_copy, err_msg="step must leave its increment untouched")
    np.testing.assert_array_equal(first.moment, second.moment, err_msg="the same input must give the same moment")
    _same(_arrays(model, first_state), _arrays(model, second_state), "the same input must give the same state")

    restored = model.state_from_arrays(model.state_to_arrays(state))
    _same(_arrays(model, restored), before, "state_from_arrays(state_to_arrays(s))")
    np.testing.assert_array_equal(model.step(restored, d_eps)[1].moment, first.moment,
                                  err_msg="a restored state must step as the original")
    index = np.array([n_cells - 1, 0, n_cells - 1])
    taken = model.take(state, index)
    _same(_arrays(model, taken), {k: v[index] for k, v in before.items()}, "take(state, index)")
    np.testing.assert_array_equal(model.step(taken, d_eps[index])[1].moment, first.moment[index],
                                  err_msg="taken cells must step as the originals")
    for i in (0, n_cells - 1):
        alone = model.step(model.take(state, np.array([i])), d_eps[i:i + 1])[1].moment
        np.testing.assert_array_equal(alone[0], first.moment[i], err_msg=f"cell {i} alone differs from its batch")

    tangent = model.step(state, d_eps, with_tangent=True)[1].tangent
    if tangent is not None:
        assert tangent.shape == (n_cells, dim, dim), "tangent shape"
        reference = central_difference_tangent(model, state, d_eps, fd_step)
        error = np.abs(tangent - reference).max(axis=(1, 2)) / np.abs(reference).max(axis=(1, 2))
        assert np.all(error <= tangent_rtol), f"tangent vs central differences: relative errors {error}"

    for name, value in model.observables(first_state).items():
        assert np.shape(value) == (n_cells,), f"observable {name!r} has shape {np.shape(value)}, not ({n_cells},)"
