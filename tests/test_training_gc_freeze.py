"""Numba's set-up is left out of later garbage collections (``training.inference._freeze_numba_setup``).

The first kernel ``FastAdvance`` loads sets numba up (~90 000 long-lived objects); after it the objects
alive are frozen (``gc.freeze``), so that later full collections do not walk them again. Objects made
afterwards are collected as usual.
"""

import gc
import weakref

import numpy as np

from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell


def test_numba_set_up_is_frozen_after_the_first_kernel_and_later_cycles_are_collected():
    cell = make_cell_model("ann", threads=1)
    state = cell.init_state(h_cell(55.0), 3)
    cell.step(state, np.tile([2e-5, 1e-5], (3, 1)))
    assert gc.get_freeze_count() > 10_000

    class Node:
        pass

    node = Node()
    node.self = node
    ref = weakref.ref(node)
    del node
    gc.collect()
    assert ref() is None
