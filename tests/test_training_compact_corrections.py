"""Compacted equilibrium corrections (``FastAdvance(compact=True)``, ``training.fast_equilibrium3d.newton3d``).

Oracle: the same corrections in one pass over every cell (``compact=False``: every cell a lane until the last
one stops, as the corrections ran before the rounds). The compacted rounds continue each cell that is still above
the tolerance from where it stopped, so every output, counts included, must be bit-identical.
"""

from pathlib import Path

import numpy as np
import pytest

from other_cpus import relaxing_network
from training.inference import COMPACT_ROUNDS, FastAdvance

ROOT = Path(__file__).resolve().parents[1]
HARD_CASES = ROOT / "tests" / "data" / "equilibrium" / "large_axial_hard.npz"


@pytest.fixture(scope="module")
def batch():
    """The hard cell-increments of a fine grain (5 to 6 Newton steps each), shuffled among copies with smaller
    probes (fewer steps) and a zero probe (no step)."""
    data = np.load(HARD_CASES)
    state = [data[name] for name in ("cell_size", "free_position", "shear_force")]
    d_eps = data["d_eps"]
    n = d_eps.shape[0]
    scale = np.repeat([1.0, 0.5, 0.1, 0.0], n)
    order = np.random.default_rng(0).permutation(scale.size)
    state = tuple(np.tile(a, (4,) + (1,) * (a.ndim - 1))[order] for a in state)
    return relaxing_network(), state, (np.tile(d_eps, (4, 1)) * scale[:, None])[order]


@pytest.mark.parametrize("corrections, tolerance", [(20, 1e-4), (20, 1e-6), (3, 1e-6), (1, 1e-6)])
def test_compacted_corrections_are_bit_identical_to_one_pass(batch, corrections, tolerance):
    net, state, d_eps = batch
    one_pass = FastAdvance(net, corrections, tolerance, compact=False)
    compacted = FastAdvance(net, corrections, tolerance)
    assert sum(compacted.rounds) == corrections and one_pass.rounds == (corrections,)
    expected = {**one_pass(*state, d_eps)._asdict(), **one_pass.last_corrections()._asdict()}
    got = {**compacted(*state, d_eps)._asdict(), **compacted.last_corrections()._asdict()}
    for name, value in expected.items():
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(value), err_msg=name)
    steps = expected["steps"]
    if corrections > COMPACT_ROUNDS[0]:
        assert (steps > COMPACT_ROUNDS[0]).any() and (steps <= COMPACT_ROUNDS[0]).any()  # later rounds ran, on some cells
    assert (steps[np.linalg.norm(d_eps, axis=1) == 0.0] == 0).all()
