"""One comparison of a compiled meso-ANN increment with the torch path (``training.cell_physics``),
shared by the planar and the spatial inference tests."""

import numpy as np

from training.cell_physics import count_held_grains
from training.network import RELAXATION_RAMP


def assert_fast_matches_torch(fast, ref, net, d: np.ndarray, fields: tuple[str, ...], rtol_of_scale: float) -> None:
    """``fast`` (the compiled increment) against ``ref`` (the torch increment of ``net`` from the same
    state, strain increments ``d`` (n_cells, dim)): each of ``fields`` within ``rtol_of_scale`` of its
    largest magnitude, the flags and held-grain counts equal, and exactly two cells below the
    relaxation ramp (the tests' states are built so)."""
    for name in fields:
        expected = getattr(ref, name).numpy()
        scale = np.abs(expected).max()
        assert scale > 0
        np.testing.assert_allclose(getattr(fast, name), expected, rtol=0, atol=rtol_of_scale * scale, err_msg=name)
    np.testing.assert_array_equal(fast.capped, ref.capped.any(dim=1).numpy())
    np.testing.assert_array_equal(fast.opened, ref.opened.any(dim=1).numpy())
    np.testing.assert_array_equal(fast.mechanism, np.all(ref.moment.numpy() == 0.0, axis=(1, 2)))
    np.testing.assert_array_equal(fast.relaxation_scaled, np.linalg.norm(d, axis=1) < RELAXATION_RAMP)
    assert fast.relaxation_scaled.sum() == 2
    np.testing.assert_array_equal(fast.grains_held, count_held_grains(net.schema, ref.held).numpy())
