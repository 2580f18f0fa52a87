"""The cell-step kernel: contact law in closed form, Warp vs numpy engines, no drift of unloaded grains."""

import math
from importlib import resources

import numpy as np
import pytest

from dem_oracle import NumpyIntegrator, h_cell_model
from warp_hcell.dem.integrator import DemIntegrator
from warp_hcell.mesostructures.files import load_mesostructure
from warp_hcell.mesostructures.mesostructure import Mesostructure
from warp_hcell.dem.model import DemModel
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.dem.state import DemState

LAW = ContactLaw()


def _rhombus(s: float) -> Mesostructure:
    """Four unit disks (D = 1) at (+-s, 0), (0, +-c), s^2 + c^2 = 1: neighbours touching, all DOFs driven."""
    c = math.sqrt(1.0 - s * s)
    return Mesostructure(name="rhombus", radius=np.full(4, 0.5), position=np.array([[s, 0], [0, c], [-s, 0], [0, -c]]),
                         driven=np.ones((4, 2), bool), pairs=np.array([[0, 1], [1, 2], [2, 3], [0, 3]]),
                         outer=np.arange(4), cell_size=np.array([2 * s, 2 * c]))


def _run(model, state, increments, engine="warp"):
    integrator = DemIntegrator(model, threads=1) if engine == "warp" else NumpyIntegrator(model)
    for d_eps in increments:
        out = DemState.empty(model.n_cells, model.meso.n_grains, model.meso.n_pairs, model.device)
        integrator.step(state, out, np.broadcast_to(d_eps, (model.n_cells, 2)))
        state = out
    return state


@pytest.mark.parametrize("s, sliding", [(0.8, False), (0.6, True)])
def test_contact_law_closed_form(device, s, sliding):
    """Axial compression e of the rhombus: overlap s^2 e, tangential displacement -s c e per contact."""
    c, e = math.sqrt(1 - s * s), 1e-4
    model = DemModel.build(_rhombus(s), 1, device=device)
    state = _run(model, model.state(), [(e, 0.0)]).to_numpy()
    # pair (0, 1): grain 1 at (s, 0), grain 2 at (0, c)
    f = state["contact_force"][0, 0]
    u = np.array([-s * (1 - e), c]) / math.hypot(s * (1 - e), c)
    normal, shear = -f @ u, f @ np.array([-u[1], u[0]])
    exact_normal = LAW.kn * (1.0 - math.hypot(s * (1 - e), c))
    assert normal == pytest.approx(exact_normal, rel=1e-9)
    assert normal == pytest.approx(LAW.kn * s * s * e, rel=2e-4)
    if sliding:  # |kt s c e| > mu kn s^2 e: the cap takes the sign of the trial force
        assert shear == pytest.approx(-LAW.mu * normal, rel=1e-12)
    else:
        assert shear == pytest.approx(-LAW.kt * s * c * e, rel=2e-4)
    assert state["shear_force"][0, 0] == pytest.approx(shear, rel=1e-12)
    # from rest the increment is driven at the refined rate; every DOF driven: no relaxation
    assert state["converged"][0] == 1 and state["substeps"][0] == math.ceil(e / DemSettings().refined_strain_per_substep)


def test_no_tension_and_history_reset_on_opening(device):
    model = DemModel.build(_rhombus(0.8), 1, device=device)
    state = _run(model, model.state(), [(1e-4, 0.0), (-3e-4, 0.0)]).to_numpy()
    assert np.all(state["contact_force"] == 0.0) and np.all(state["shear_force"] == 0.0)
    assert np.all(state["contact"] == 0)


def test_touching_grains_are_contacts_from_the_start(device):
    """Exactly touching H-cell: six zero-force contacts; the smallest compression loads all of them."""
    model = h_cell_model(55.0, 1, 0.5, device=device)
    initial = model.state().to_numpy()
    labelled = model.meso.pair_label > 0
    assert np.all(initial["contact"][0, labelled] == 1) and np.all(initial["contact"][0, ~labelled] == 0)
    state = _run(model, model.state(), [(1e-7, 1e-7)]).to_numpy()
    normal = np.linalg.norm(state["contact_force"][0], axis=1)
    assert np.all(normal[labelled] > 0.0) and np.all(normal[~labelled] == 0.0)


def _mixed_increments(rng, n_cells, n_steps):
    """Per-cell increments of magnitudes 1e-6..3e-4 in all directions, after an isotropic compression."""
    steps = [np.full((n_cells, 2), 4e-4)]
    for _ in range(n_steps):
        steps.append(rng.uniform(-1, 1, (n_cells, 2)) * 10 ** rng.uniform(-6, -3.5, (n_cells, 1)))
    return steps


@pytest.mark.parametrize("source", ["h_cell", "h_cell_fine_grain.toml"])
def test_warp_and_numpy_engines_agree(device, source):
    rng = np.random.default_rng(7)
    n_cells = 12
    meso = None if source == "h_cell" else load_mesostructure(resources.files("warp_hcell") / "data" / source)
    alpha0 = rng.uniform(32.0, 85.0, n_cells)
    build = (lambda dev: h_cell_model(alpha0, n_cells, 0.5, device=dev)) if meso is None else (
        lambda dev: DemModel.build(meso, n_cells, device=dev))
    increments = _mixed_increments(rng, n_cells, 4)
    warp_model, numpy_model = build(device), build("cpu")
    a = _run(warp_model, warp_model.state(), increments).to_numpy()
    b = _run(numpy_model, numpy_model.state(), increments, engine="numpy").to_numpy()
    assert np.abs(b["contact_force"]).max() > 1e4 and np.all(a["converged"] == 1)
    # the same floating-point operations in the same order: bit for bit
    for name in a:
        assert np.array_equal(a[name], b[name]), name


def test_unloaded_free_grains_do_not_drift(device):
    """Open H-cells (mechanism state): free coordinates stay put and velocities are zero."""
    model = h_cell_model(np.array([45.0, 55.0, 70.0]), 3, 0.5, device=device)
    state = _run(model, model.state(), [(2e-4, 2e-4), (-6e-4, -6e-4)])
    before = state.to_numpy()
    assert np.all(before["contact_force"] == 0.0)
    after = _run(model, state, [(0.0, -2e-4), (1e-5, -1e-4)]).to_numpy()
    free = ~model.meso.driven
    assert np.array_equal(after["position"][:, free], before["position"][:, free])
    assert np.all(after["velocity"][:, free] == 0.0) and np.all(after["converged"] == 1)


def test_strain_per_substep_grows_along_a_path_and_restarts_on_reversal(device):
    """Every DOF driven (no relaxation): from rest the increment is driven at the refined rate,
    the rate then doubles per increment up to strain_per_substep, and a reversal starts again
    from the refined rate. Each step's increment is e = 1e-4 along n."""
    settings, e = DemSettings(), 1e-4
    model = DemModel.build(_rhombus(0.8), 1, device=device)
    integrator = DemIntegrator(model, threads=1)
    state, counts = model.state(), []
    for d in [e] * 5 + [-e]:
        out = DemState.empty(1, 4, 4, model.device)
        integrator.step(state, out, np.array([[d, 0.0]]))
        counts.append(int(out.substeps.numpy()[0]))
        state = out
    fine, coarse = math.ceil(e / settings.refined_strain_per_substep), math.ceil(e / settings.strain_per_substep)
    assert counts[0] == fine and counts[-1] == fine
    assert counts[1:5] == sorted(counts[1:5], reverse=True) and counts[1] < fine and counts[4] == coarse


def test_kernel_love_weber_sum_and_area_match_the_host_formulas(device):
    """The kernel's per-cell Love-Weber sum and V_cell equal sum_p f_p (x) b_p and the shoelace
    area computed on the host from its output forces and positions."""
    from warp_hcell.database.learning_state import love_weber_tension_positive
    from warp_hcell.mesostructures.mesostructure import polygon_area

    rng = np.random.default_rng(11)
    model = h_cell_model(rng.uniform(35.0, 80.0, 8), 8, 0.5, device=device)
    state = _run(model, model.state(), _mixed_increments(rng, 8, 3)).to_numpy()
    pairs = model.meso.pairs
    branch = state["position"][:, pairs[:, 1]] - state["position"][:, pairs[:, 0]]
    expected = love_weber_tension_positive(state["contact_force"], branch)
    assert np.abs(expected).max() > 1e3
    np.testing.assert_allclose(state["moment"], expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(state["area"], polygon_area(state["position"], model.meso.outer), rtol=1e-14)
