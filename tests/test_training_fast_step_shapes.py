"""``FastAdvance.increment`` checks the state's shapes on every call, also once its scratch arrays exist.

The check compares the shapes with those its workspace was made for; a call of another number of cells
makes a new workspace, a call whose shapes fit no number of cells is refused (ValueError) and leaves the
workspace of the earlier calls as it was (``last_counts``, ``last_features`` still read it).
"""

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell


@pytest.fixture(scope="module")
def cell():
    return make_cell_model("ann", threads=1)


def _probe(n: int) -> np.ndarray:
    return np.tile([2e-5, 1e-5], (n, 1))


def test_a_bad_state_is_refused_after_good_calls_and_leaves_their_workspace(cell):
    fast = cell.fast
    state = cell.init_state(h_cell(55.0), 5)
    first, _ = fast.increment(*state, _probe(5))
    features = fast.last_features().copy()
    size, free, shear = state
    bad = [(size, free, shear, _probe(4)), (size[:, :1], free, shear, _probe(5)), (size, free[:, :3], shear, _probe(5)),
           (size, free, shear[:, :14], _probe(5)), (size, free, shear, _probe(5)[:, :1])]
    for arrays in bad:
        with pytest.raises(ValueError, match="expected"):
            fast.increment(*arrays)
        np.testing.assert_array_equal(fast.last_features(), features)
    again, _ = fast.increment(*state, _probe(5))
    np.testing.assert_array_equal(again.moment, first.moment)


def test_another_number_of_cells_takes_its_own_workspace(cell):
    fast = cell.fast
    for n in (3, 7, 3):
        inc, _ = fast.increment(*cell.init_state(h_cell(55.0), n), _probe(n))
        assert inc.area.shape == (n,) and fast.last_features().shape[1] == n
        assert np.all(np.isfinite(inc.moment))
