"""DemState: numpy round trip with dtype casting, empty allocation, the pool of step outputs."""

import numpy as np

from dem_oracle import h_cell_model
from warp_hcell.dem.cell import DemCell
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.dem.model import DemModel
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.dem.state import DemState, StatePool


def test_numpy_round_trip_casts_to_the_field_types(device):
    arrays = h_cell_model(55.0, 2, 0.5).state().to_numpy()
    arrays["contact"] = arrays["contact"].astype(np.int64)  # e.g. read back from HDF5
    arrays["position"] = arrays["position"].astype(np.float32).astype(np.float64)
    state = DemState.from_numpy(arrays, device)
    back = state.to_numpy()
    assert back["contact"].dtype == np.int32 and back["position"].dtype == np.float64
    for name, value in arrays.items():
        assert np.array_equal(back[name], value), name
    assert state.n_cells == 2


def test_empty_shapes(device):
    state = DemState.empty(5, 7, 21, device)
    shapes = {k: v.shape for k, v in state.to_numpy().items()}
    assert shapes == {"position": (5, 7, 2), "velocity": (5, 7, 2), "shear_force": (5, 21),
                      "contact_force": (5, 21, 2), "contact": (5, 21), "cell_size": (5, 2),
                      "moment": (5, 2, 2), "area": (5,), "substeps": (5,), "converged": (5,)}


def test_empty_fields_do_not_overlap_and_outlive_the_state(device):
    """The fields share one allocation: writing each one leaves the others intact, and a numpy
    view keeps its memory after the state is gone."""
    state = DemState.empty(7, 6, 15, device)
    for k, name in enumerate(("position", "velocity", "shear_force", "contact_force", "contact", "cell_size",
                              "moment", "area", "substeps", "converged")):
        field = getattr(state, name)
        field.assign(np.full(field.numpy().shape, k + 1, dtype=field.numpy().dtype))
    arrays = state.to_numpy()
    for k, name in enumerate(arrays):
        assert np.all(arrays[name] == k + 1), name
    if device == "cpu":
        view = state.moment.numpy()
        del state, arrays
        DemState.empty(7, 6, 15, device).moment.fill_(0.0)
        assert np.all(view == 7)


def test_pool_reuses_only_states_nobody_refers_to():
    pool = StatePool(4, 6, 15, "cpu", capacity=2)
    first = pool.acquire()
    assert pool.acquire() is not first  # still held here
    first_id = id(first)
    del first
    again = pool.acquire()
    assert id(again) == first_id  # dropped: reused
    view = again.position.numpy()  # a numpy view of a field keeps the state out of reuse
    del again
    assert id(pool.acquire()) != first_id
    del view
    assert id(pool.acquire()) == first_id


def test_dem_steps_never_overwrite_a_state_the_caller_keeps():
    cell = DemCell(ContactLaw(), 0.5, threads=1)
    state = cell.init_state(h_cell(55.0), 3)
    d_eps = np.full((3, 2), 1e-4)
    kept = []
    for _ in range(12):  # more steps than the pool keeps states
        state, _ = cell.step(state, d_eps)
        kept.append((state, state.dem.position.numpy().copy()))
    for held, position in kept:
        np.testing.assert_array_equal(held.dem.position.numpy(), position)
