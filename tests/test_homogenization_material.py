"""Homogenised material: stress as the driver's, consistent tangent against central differences."""

import numpy as np
import pytest

from cell_doubles import ElasticCell
from homogenization.material import orientation
from homogenization.backends import make_cell_model
from homogenization.material.homogenised import HomogenisedMaterial
from warp_hcell.mesostructures.hcell import h_cell


def _loaded(model, n_orientations=24, alpha0=(40.0, 55.0, 40.0)):
    """Points compressed isotropically then sheared along different directions (shear included)."""
    orient = orientation.orientations(n_orientations)
    material = HomogenisedMaterial(model, orient, [h_cell(a) for a in alpha0], len(alpha0))
    state = material.init_state()
    iso = np.tile([2e-4, 2e-4, 0.0], (len(alpha0), 1))
    for _ in range(50):
        state = material.update(state, iso, with_tangent=False).state
    shear = np.array([[2e-4, -1e-4, 0.0], [1e-4, -2e-4, 1e-4], [0.0, 0.0, 3e-4]])
    for _ in range(20):
        state = material.update(state, shear, with_tangent=False).state
    return material, state, shear


def _fd(material, state, d_e, h):
    out = np.empty((material.n_points, 3, 3))
    for j in range(3):
        plus, minus = d_e.copy(), d_e.copy()
        plus[:, j] += h
        minus[:, j] -= h
        out[:, :, j] = (material.update(state, plus, with_tangent=False).stress
                        - material.update(state, minus, with_tangent=False).stress) / (2 * h)
    return out


@pytest.mark.parametrize("model", [ElasticCell(), make_cell_model("analytical")], ids=["elastic", "analytical"])
def test_tangent_matches_central_differences(model):
    material, state, d_e = _loaded(model)
    update = material.update(state, d_e)
    reference = _fd(material, state, d_e, 1e-8)
    scale = np.abs(reference).max(axis=(1, 2))
    error = np.abs(update.tangent - reference).max(axis=(1, 2)) / scale
    assert error.max() <= 5e-7, error  # docs/studies/bvp_tangent_accuracy.md: 1.1e-7 (analytical)
    # plane strain, isotropic fabric: the shear row is not trivial
    assert np.abs(update.tangent[:, 2, 2]).min() > 1e-3 * scale.min()


def test_one_batched_step_call_and_purity():
    calls = []
    model = ElasticCell()
    original = model.step

    def counting(state, d, *, with_tangent=False):
        calls.append(d.shape[0])
        return original(state, d, with_tangent=with_tangent)

    model.step = counting
    material, state, d_e = _loaded(model, n_orientations=12)
    calls.clear()
    first = material.update(state, d_e)
    again = material.update(state, d_e)
    assert calls == [3 * 12, 3 * 12]
    np.testing.assert_array_equal(first.stress, again.stress)


def test_stress_and_volume_rule_match_the_driver():
    """A homogeneous strain path through the material gives the driver's stresses and J."""
    from homogenization.element_test import driver, programme as programmes

    model = make_cell_model("analytical")
    programme = (programmes.proportional_strain(4e-3, 4e-3, 20, label="iso"), programmes.constant_volume_biaxial(0.01, 20))
    record = driver.run(model, programme, mesostructure=h_cell(40.0), n_orientations=36, progress=False)
    material = HomogenisedMaterial(model, orientation.orientations(36), h_cell(40.0), 1)
    state = material.init_state()
    increments = np.diff(np.stack([record.eps11, record.eps22], axis=1), axis=0, prepend=np.zeros((1, 2)))
    stresses = []
    for d in increments:
        state = material.update(state, np.array([[d[0], d[1], 0.0]]), with_tangent=False).state
        stresses.append(state.stress[0])
    stresses = np.array(stresses)
    np.testing.assert_allclose(stresses[:, 0], record.sigma11, rtol=1e-12)
    np.testing.assert_allclose(stresses[:, 1], record.sigma22, rtol=1e-12)
    assert state.J[0] == pytest.approx(record.J[-1], rel=1e-14)


def test_backend_without_tangent_steps_plainly_and_refuses_tangents():
    """A backend whose step takes no with_tangent still runs strain-controlled updates."""

    class NoTangent(ElasticCell):
        def step(self, state, d_eps_local):
            return super().step(state, d_eps_local)

    material, state, d_e = _loaded(NoTangent(), n_orientations=6)
    assert not material.returns_tangent
    assert material.update(state, d_e, with_tangent=False).tangent is None
    with pytest.raises(ValueError, match="^cell model 'elastic' returns no consistent tangent"):
        material.update(state, d_e)


def test_points_are_independent():
    """A point's result does not depend on the other points of the batch."""
    model = make_cell_model("analytical")
    material, state, d_e = _loaded(model)
    full = material.update(state, d_e)
    single = HomogenisedMaterial(model, material.orient, h_cell(55.0), 1)
    single.init_state()
    cells = model.take(state.cells, np.arange(24, 48))
    from homogenization.material.homogenised import MaterialState

    one = MaterialState(cells, state.J[1:2], state.strain[1:2], state.stress[1:2])
    alone = single.update(one, d_e[1:2])
    np.testing.assert_array_equal(alone.stress[0], full.stress[1])
    np.testing.assert_array_equal(alone.tangent[0], full.tangent[1])
