"""Fast inference path (``training.inference.FastAdvance``) against the autograd path ``MesoNet.advance``.

Uses the shipped default model on loaded H-cells, including cells with capped tangential forces,
zero and tiny probes (relaxation ramp). Tolerances are relative to the largest value of each
output: the tangential force, kt times a difference of nearly equal branch vectors, carries
rounding of ~1e-11 of it in float64.
"""

import numpy as np
import pytest
import torch

from homogenization.backends.ann import AnnCell
from training.inference import FastAdvance
from training.network import RELAXATION_RAMP
from warp_hcell.parameters import ContactLaw


@pytest.fixture(scope="module")
def loaded():
    cell = AnnCell(ContactLaw(), 0.5)
    rng = np.random.default_rng(1)
    n = 40
    state = cell.init_state(rng.uniform(35.0, 65.0, n), n)
    shear = np.stack([np.ones(n), -np.ones(n)], axis=1) * rng.choice([-1.0, 1.0], size=(n, 1))
    for k in range(80):
        state, _ = cell.step(state, np.full((n, 2), 4e-4) if k < 30 else 2e-4 * shear)
    d = 1e-4 * shear + rng.normal(scale=2e-5, size=(n, 2))
    d[0] = 0.0
    d[1] = [3e-8, 0.0]
    return cell, state, d


def _reference(cell, state, d):
    with torch.inference_mode():
        return cell.net.advance(*(torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in state),
                                torch.from_numpy(d))


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-9), (torch.float32, 1e-6)])
def test_fast_increment_equals_the_autograd_path(loaded, dtype, rtol):
    cell, state, d = loaded
    ref = _reference(cell, state, d)
    fast = FastAdvance(cell.net, dtype)(*state, d)
    for name in ("cell_size", "free_position", "shear_force", "moment", "area"):
        expected = getattr(ref, name).numpy()
        scale = np.abs(expected).max()
        assert scale > 0
        np.testing.assert_allclose(getattr(fast, name), expected, rtol=0, atol=rtol * scale, err_msg=name)
    np.testing.assert_array_equal(fast.capped, ref.capped.any(dim=1).numpy())
    np.testing.assert_array_equal(fast.opened, ref.opened.any(dim=1).numpy())
    np.testing.assert_array_equal(fast.mechanism, np.all(ref.moment.numpy() == 0.0, axis=(1, 2)))
    np.testing.assert_array_equal(fast.relaxation_scaled, np.linalg.norm(d, axis=1) < RELAXATION_RAMP)
    assert fast.relaxation_scaled.sum() == 2


def test_the_states_exercise_the_contact_law_branches(loaded):
    cell, state, d = loaded
    ref = _reference(cell, state, d)
    assert ref.capped.any() and (~ref.capped.any(dim=1)).any()
    assert (np.asarray(state.shear_force) != 0).any()
