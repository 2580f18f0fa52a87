"""The compiled tangent of the corrected 3D meso-ANN step (``training.fast_equilibrium3d.balance_tangent3d``,
``FastAdvance.has_tangent``) against torch autograd of ``training.equilibrium.corrected_advance`` (implicit
derivative of the balance, the contact law in torch), which nobody derived the same way here.

Measured: within 3.2e-16 of the largest entry on 30 sheared cells of the shipped 3D model, every cell
corrected; the tolerance is 5 times that rounded up. A spatial network without corrections has no compiled
tangent (its tangent stays torch autograd of the network)."""

import numpy as np
import pytest

from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell3D
from warp_hcell.core.parameters import ContactLaw
from warp_hcell.mesostructures.builders import mesostructure_arg

needs_model = pytest.mark.skipif(not default_model_path(3).is_file(), reason="no shipped 3D model")


@pytest.fixture(scope="module")
def sheared():
    """30 cells of the shipped model compressed isotropically then sheared at random deviatoric rates."""
    cell = AnnCell3D(ContactLaw(), 0.5)
    rng = np.random.default_rng(0)
    n = 30
    state = cell.init_state(mesostructure_arg("hcell3d:alpha0=55").build(55.0), n)
    for k in range(300):
        d = (np.full((n, 3), 1e-4) if k < 100 else
             np.column_stack([np.full(n, 1e-4), -0.5e-4 + 3e-5 * rng.standard_normal(n),
                              -0.5e-4 + 3e-5 * rng.standard_normal(n)]))
        state, _ = cell.step(state, d)
    return state, np.tile([1e-4, -0.5e-4, -0.5e-4], (n, 1))


@needs_model
def test_the_compiled_tangent_of_corrected_cells_is_torch_autograd(sheared):
    state, d_eps = sheared
    cell = AnnCell3D(ContactLaw(), 0.5, equilibrium_corrections=3)
    assert cell.fast.has_tangent
    _, compiled = cell.step(state, d_eps, with_tangent=True)
    steps = cell.fast.last_corrections().steps
    fast, cell.fast = cell.fast, None
    _, reference = cell.step(state, d_eps, with_tangent=True)
    cell.fast = fast
    corrected = steps > 0
    assert corrected.sum() >= 20
    scale = np.abs(reference.tangent).max()
    assert scale > 0
    assert np.abs(compiled.tangent[corrected] - reference.tangent[corrected]).max() <= 2e-15 * scale


@needs_model
def test_a_spatial_network_alone_has_no_compiled_tangent():
    cell = AnnCell3D(ContactLaw(), 0.5)
    assert not cell.fast.has_tangent
    with pytest.raises(ValueError, match="planar, or of corrected spatial cells"):
        state = cell.init_state(mesostructure_arg("hcell3d:alpha0=55").build(55.0), 2)
        cell.fast.increment(*state, np.full((2, 3), 1e-4), with_tangent=True)
