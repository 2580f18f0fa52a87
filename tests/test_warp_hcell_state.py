"""DemState: numpy round trip with dtype casting, empty allocation."""

import numpy as np

from warp_hcell.model import DemModel
from warp_hcell.state import DemState


def test_numpy_round_trip_casts_to_the_field_types(device):
    arrays = DemModel.build_h_cell(55.0, 2, 0.5).state().to_numpy()
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
