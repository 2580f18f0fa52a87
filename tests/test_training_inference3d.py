"""The compiled increment of spatial cells (``training.fast_step3d`` in ``training.inference.FastAdvance``)
against the torch path ``MesoNet.advance``, on the shipped 3D model (ten-sphere H-cell).

What is bit-identical: given the same free-DOF displacement, the compiled physics gives the torch
path's new cell size and free positions (the rest rule included) bit for bit; its springs, moment
and volume differ by summation order only (within 1e-14 of the largest value; measured 3e-16,
2.4e-15 and 4e-16). A cell's compiled increment is bit-identical in any batch, at any place, and
under other CPUs' compile targets. Against the float64 torch path (float32 network): one step
within 1e-7 of the largest value of each output (measured up to 4e-8 of the moment from a
force-free state, ~1e-9 from loaded ones), and a short undrained triaxial run within 4e-8 of p0
(measured 8e-9).
"""

import numpy as np
import pytest
import torch

from fast_vs_torch import assert_fast_matches_torch
from other_cpus import OTHER_CPUS, spatial_loaded
from homogenization.ann import default_model_path
from training import cell_physics
from training.fast_tables import Advanced, Before
from training.fast_step3d import features3d, physics3d
from training.inference import _cells_last
from warp_hcell.mesostructures.builders import mesostructure_arg

needs_model = pytest.mark.skipif(not default_model_path(3).is_file(), reason="no shipped 3D model")
STATE_FIELDS = ("cell_size", "free_position", "shear_force", "moment", "area")


@pytest.fixture(scope="module")
def loaded():
    """40 spatial cells compressed isotropically, then sheared at random deviatoric rates until
    contacts slide; the probes include a zero one and one below the relaxation ramp."""
    return spatial_loaded()


def _reference(cell, state, d):
    with torch.inference_mode():
        return cell.net.advance(*(torch.from_numpy(np.asarray(a, dtype=np.float64)) for a in state),
                                torch.from_numpy(d))


@needs_model
def test_the_states_exercise_the_contact_law_branches(loaded):
    cell, state, d = loaded
    ref = _reference(cell, state, d)
    assert ref.capped.any() and (~ref.capped.any(dim=1)).any()
    assert np.abs(np.asarray(state.shear_force)).max() > 0


@needs_model
def test_the_compiled_increment_equals_the_torch_path(loaded):
    cell, state, d = loaded
    fast = cell.fast(*state, d)
    ref = _reference(cell, state, d)
    assert_fast_matches_torch(fast, ref, cell.net, d, STATE_FIELDS, 1e-7)


@needs_model
def test_given_the_same_displacement_the_compiled_physics_is_the_torch_physics(loaded):
    cell, state, d = loaded
    tensors = [torch.from_numpy(np.asarray(a)) for a in state]
    with torch.inference_mode():
        d_free = cell.net.displacement(*tensors, torch.from_numpy(d))
        ref = cell_physics.advance(cell.net.schema, *tensors, torch.from_numpy(d), d_free, rest_rule=True)
    fast, n = cell.fast, d.shape[0]
    n_free, n_pairs = fast.cells.free_dofs.shape[0], fast.cells.pairs.shape[0]
    size, free, shear = (_cells_last(a) for a in state)
    before = Before(np.empty((fast.scaling.feature_mean.shape[0], n), dtype=np.float32), np.empty(n),
                    np.empty((n_free, n)), np.empty((n_pairs, 3, n)), np.empty((n_pairs, n), dtype=np.bool_),
                    np.empty((n_pairs, n)))
    features3d(size, free, shear, d, fast.cells, fast.law, fast.scaling, before)
    flags = np.empty((4, n), dtype=np.bool_)
    out = Advanced(np.empty((3, n)), np.empty((n_free, n)), np.empty((n_pairs, 3, n)), np.empty((n, 3, 3)),
                   np.empty(n), *flags, np.empty(n, dtype=np.int64), np.empty((n_free, n), dtype=np.bool_))
    physics3d(size, free, shear, d, np.ascontiguousarray(d_free.numpy().T), fast.cells, fast.law, before, out)
    np.testing.assert_array_equal(out.new_size.T, ref.cell_size.numpy())
    np.testing.assert_array_equal(out.new_free.T, ref.free_position.numpy())
    np.testing.assert_array_equal(out.held_dof.T, ref.held.numpy())
    for name, value in (("shear_force", np.moveaxis(out.new_shear, -1, 0)), ("moment", out.moment),
                        ("area", out.area)):
        expected = getattr(ref, name).numpy()
        np.testing.assert_allclose(value, expected, rtol=0, atol=1e-14 * np.abs(expected).max(), err_msg=name)


@needs_model
def test_a_cells_increment_is_bit_identical_in_any_batch_at_any_place(loaded):
    cell, state, d = loaded
    whole = cell.fast(*state, d)
    for index in (np.array([7]), np.array([39, 3, 3, 20]), np.arange(40)[::-1]):
        part = cell.fast(*(np.asarray(a)[index] for a in state), d[index])
        for name in part._fields:
            np.testing.assert_array_equal(getattr(part, name), getattr(whole, name)[index], err_msg=name)


@needs_model
@pytest.mark.other_cpus("spatial")
@pytest.mark.parametrize("setting", list(OTHER_CPUS))
def test_a_cells_increment_does_not_depend_on_the_cpus_vector_width(other_cpus, setting):
    """The compiled step of ``loaded`` re-run in a process compiled for another CPU (``tests/other_cpus.py``): every
    field bit-identical to this process, whole batch and sub-batch."""
    here, index, other = other_cpus.compare("spatial", setting)
    for name, value in here.items():
        np.testing.assert_array_equal(other[f"whole_{name}"], value, err_msg=f"{name}, {setting}")
        np.testing.assert_array_equal(other[f"part_{name}"], value[index], err_msg=f"{name} of a sub-batch, {setting}")


@needs_model
def test_the_backend_steps_spatial_cells_compiled_and_takes_their_tangent_from_torch(loaded):
    cell, state, d = loaded
    new, response = cell.step(state, d)
    fast = cell.fast(*state, d)
    np.testing.assert_array_equal(response.moment, fast.moment)
    assert response.tangent is None and response.diagnostics["n_coulomb_capped"] == np.count_nonzero(fast.capped)
    with pytest.raises(ValueError, match="planar"):
        cell.fast.increment(*state, d, with_tangent=True)
    _, with_tangent = cell.step(state, d, with_tangent=True)
    assert with_tangent.tangent.shape == (40, 3, 3) and np.isfinite(with_tangent.tangent).all()
    np.testing.assert_allclose(with_tangent.moment, fast.moment, rtol=0, atol=1e-7 * np.abs(fast.moment).max())


@needs_model
def test_a_short_undrained_triaxial_run_follows_the_torch_path():
    from homogenization.element_test import driver, programme as programmes
    from homogenization.backends import make_cell_model

    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    programme = programmes.triaxial(2e5, 0.01, 1e-4, test="undrained", iso_increment=5e-5)
    runs = []
    for compiled in (True, False):
        model = make_cell_model("ann", dim=3)
        if not compiled:
            model.fast = None
        runs.append(driver.run(model, programme, mesostructure=meso, lebedev_order=11, n_spins=4, progress=False))
    assert runs[0].n_increments == runs[1].n_increments and runs[0].q.max() > 0.25 * 2e5
    for name in ("sigma11", "sigma22", "sigma33", "p", "q"):
        np.testing.assert_allclose(getattr(runs[0], name), getattr(runs[1], name), rtol=0, atol=4e-8 * 2e5,
                                   err_msg=name)


@needs_model
def test_the_compiled_features_are_the_torch_features(loaded):
    """The z-scored features the compiled step leaves (which the out-of-distribution check reads) are the
    torch path's, load fractions included, to float32 rounding."""
    cell, state, d = loaded
    cell.fast(*state, d)
    with torch.inference_mode():
        raw = cell.net.raw_features(*(torch.from_numpy(np.asarray(a)) for a in state), torch.from_numpy(d))[0]
        expected = ((raw - cell.net.feature_mean) / cell.net.feature_std).numpy()
    assert cell.net.load_features and expected.shape[1] == cell.fast.last_features().shape[0]
    np.testing.assert_allclose(cell.fast.last_features().T, expected, rtol=1e-6, atol=1e-6)


@needs_model
def test_asking_for_the_tangent_leaves_the_step_the_compiled_one():
    """The spatial network alone has no compiled tangent (torch's autograd gives it), but its state and moment
    are the compiled step's whether the tangent is asked or not (they were torch's, 1e-9 apart, with it), so a
    stress-controlled run accepts the same bits as a strain-controlled one would."""
    from homogenization.ann.cell import AnnCell3D  # noqa: PLC0415
    from warp_hcell.core.parameters import ContactLaw  # noqa: PLC0415

    cell = AnnCell3D(ContactLaw(), 0.5, model=default_model_path(3))
    state = cell.init_state(mesostructure_arg("hcell3d:alpha0=55").build(None), 8)
    for _ in range(20):
        state, _ = cell.step(state, np.full((8, 3), 2e-4))
    d_eps = 1e-4 * np.random.default_rng(0).normal(size=(8, 3))
    plain, response = cell.step(state, d_eps)
    asked, with_tangent = cell.step(state, d_eps, with_tangent=True)
    assert all(np.array_equal(a, b) for a, b in zip(plain, asked))
    assert np.array_equal(response.moment, with_tangent.moment) and with_tangent.tangent.shape == (8, 3, 3)
    assert np.isfinite(with_tangent.tangent).all()
