"""Integrators: increment validation, state_in untouched, per-cell substep counts."""

import numpy as np
import pytest

from dem_oracle import NumpyIntegrator, h_cell_model
from warp_hcell.dem.integrator import DemIntegrator, MIN_CELLS_TO_SPLIT
from warp_hcell.dem.model import DemModel
from warp_hcell.core.parameters import DemSettings
from warp_hcell.dem.state import DemState


def _model(n_cells=3, **settings):
    return h_cell_model(np.linspace(40.0, 70.0, n_cells), n_cells, 0.5, settings=DemSettings(**settings))


@pytest.mark.parametrize("d_eps, message", [
    (np.zeros((2, 2)), r"d_eps_local has shape \(2, 2\), expected \(3, 2\)"),
    (np.full((3, 2), np.nan), "d_eps_local contains non-finite values"),
    (np.full((3, 2), 1.0), r"strain increment 1 must be < 1 in magnitude \(l <- l \(1 - d_eps\)\)"),
    (np.full((3, 2), 1e-3), "strain increment 0.001 is too large for max_substeps = 100 at 5e-06 per substep"),
])
def test_bad_increments_are_refused(d_eps, message):
    model = _model(max_substeps=100)
    with pytest.raises(ValueError, match=message):
        DemIntegrator(model, threads=1).step(model.state(), DemState.empty(3, 6, 15, "cpu"), d_eps)


@pytest.mark.parametrize("engine", ["warp", "numpy"])
def test_state_in_is_not_written_and_substeps_follow_each_increment(engine):
    model = _model()
    state_in = model.state()
    before = {k: v.copy() for k, v in state_in.to_numpy().items()}
    integrator = DemIntegrator(model, threads=2) if engine == "warp" else NumpyIntegrator(model)
    out = DemState.empty(3, 6, 15, "cpu")
    d_eps = np.array([[1e-6, 0.0], [2e-5, 1e-5], [-3e-4, 1e-4]])
    integrator.step(state_in, out, d_eps)
    for name, value in state_in.to_numpy().items():
        assert np.array_equal(value, before[name]), name
    n_drive = np.ceil(np.abs(d_eps).max(axis=1) / DemSettings().strain_per_substep)
    substeps = out.substeps.numpy()
    assert np.all(substeps >= n_drive) and np.all(out.converged.numpy() == 1)
    np.testing.assert_allclose(out.cell_size.numpy(), before["cell_size"] * (1.0 - d_eps), rtol=1e-15)


def test_threads_must_be_positive():
    with pytest.raises(ValueError, match="threads = 0 must be >= 1"):
        DemIntegrator(_model(), threads=0)


def test_small_batches_split_over_the_threads_with_the_same_cells():
    n = MIN_CELLS_TO_SPLIT + 5
    model = _model(n)
    rng = np.random.default_rng(11)
    d_eps = rng.uniform(-1e-4, 1e-4, (n, 2))
    results = []
    for threads in (1, 2):
        integrator = DemIntegrator(model, threads=threads)
        out = DemState.empty(n, 6, 15, "cpu")
        integrator.step(model.state(), out, d_eps)
        results.append((len(integrator._launches), out.to_numpy()))
    (launches_1, one), (launches_2, two) = results
    assert (launches_1, launches_2) == (1, 2)
    for name in one:
        assert np.array_equal(one[name], two[name]), name
    # below the threshold: one launch on the calling thread
    assert len(DemIntegrator(_model(MIN_CELLS_TO_SPLIT - 1), threads=2)._launches) == 1
