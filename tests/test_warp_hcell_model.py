"""DemModel: replication, per-cell templates, masses and time steps, gathering, initial state."""

import math
from importlib import resources

import numpy as np
import pytest

from dem_oracle import h_cell_model
from warp_hcell.mesostructures.hcell import h_cell
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.mesostructure import MesostructureError
from warp_hcell.dem.model import DemModel
from warp_hcell.core.parameters import ContactLaw, DemSettings

DATA = resources.files("warp_hcell") / "data"


def test_per_cell_templates_equal_the_vectorised_h_cell_batch(device):
    alphas = [35.0, 55.0, 80.0]
    stacked = DemModel.build([h_cell(a, 0.5) for a in alphas], 3, device=device)
    batch = h_cell_model(np.array(alphas), 3, 0.5, device=device)
    for name in ("radius", "inv_mass", "reference_position", "reference_cell_size", "dt", "force_floor"):
        assert np.array_equal(getattr(stacked, name).numpy(), getattr(batch, name).numpy()), name


def test_masses_time_step_and_force_floor_follow_the_settings():
    law, settings = ContactLaw(kn=1e7), DemSettings(density=1000.0, dt_factor=0.1, contact_tolerance=1e-8)
    meso = load_mesostructure(DATA / "h_cell_lateral_0.7D.toml")
    model = DemModel.build(meso, 2, contact_law=law, settings=settings)
    mass = 1000.0 * math.pi * np.array([0.5, 0.35, 0.35, 0.5, 0.35, 0.35]) ** 2
    np.testing.assert_allclose(model.inv_mass.numpy()[1], 1.0 / mass, rtol=1e-15)
    # the lightest grain sets the time step of its cell
    np.testing.assert_allclose(model.dt.numpy(), 0.1 * math.sqrt(1000.0 * math.pi * 0.35**2 / 1e7), rtol=1e-15)
    np.testing.assert_allclose(model.force_floor.numpy(), 1e7 * 1e-8 * 2 * np.mean(meso.radius), rtol=1e-15)


def test_replicated_model_and_initial_state():
    model = DemModel.build(h_cell(55.0, 0.5), 4)
    state = model.state().to_numpy()
    assert model.n_cells == 4
    assert np.array_equal(state["position"], np.broadcast_to(h_cell(55.0, 0.5).position, (4, 6, 2)))
    assert np.all(state["velocity"] == 0.0) and np.all(state["shear_force"] == 0.0)
    assert np.array_equal(state["contact"][0], (model.meso.pair_label > 0).astype(np.int32))


def test_take_gathers_cells_with_repetition():
    model = h_cell_model(np.array([35.0, 55.0, 80.0]), 3, 0.5)
    taken = model.take(np.array([2, 2, 0]))
    assert np.array_equal(taken.reference_position.numpy(), model.reference_position.numpy()[[2, 2, 0]])
    assert taken.meso is model.meso and taken.n_cells == 3


def test_templates_must_share_one_topology():
    other = load_mesostructure(DATA / "h_cell_fine_grain.toml")
    with pytest.raises(MesostructureError, match="has another topology than"):
        DemModel.build([h_cell(55.0, 0.5), other], 2)
    with pytest.raises(ValueError, match=r"need one mesostructure or n_cells = 3 of them, got 2"):
        DemModel.build([h_cell(55.0, 0.5)] * 2, 3)
