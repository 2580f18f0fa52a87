"""A stress-controlled run with the meso-ANN that cannot converge stops with a one-line diagnosis: which
cells failed their step or tangent at the last trial, the certificate's verdict and whether the run
lies inside the certificate's envelope (``AnnCell.control_diagnosis``, ``homogenization.element_test.driver.run``);
``hmodel triaxial`` prints it on one line with exit code 2. The failing case is contrived: two cells
of the shipped 3D model whose step turns non-finite after a number of step calls."""

import numpy as np
import pytest

from homogenization import hmodel
from homogenization.element_test import driver, programme as programmes
from homogenization.backends import make_cell_model
from homogenization.ann import default_model_path
from homogenization.ann.cell import AnnCell, AnnCell3D
from warp_hcell.core.contract import CellResponse
from warp_hcell.mesostructures.builders import mesostructure_arg

pytestmark = pytest.mark.skipif(not default_model_path(3).is_file(), reason="no shipped 3D model")
BROKEN = (3, 7)
"""Cells of the 100-cell rule (Lebedev order 11 x 4 spins) whose contrived step fails."""


def _break(monkeypatch, after: int) -> None:
    """AnnCell.step gives NaN moments (and tangents) for the ``BROKEN`` cells from its ``after``-th call on."""
    original = AnnCell.step
    calls = [0]

    def step(self, state, d_eps_local, *, with_tangent=False):
        new, response = original(self, state, d_eps_local, with_tangent=with_tangent)
        calls[0] += 1
        if calls[0] < after:
            return new, response
        moment = np.array(response.moment)
        moment[list(BROKEN)] = np.nan
        tangent = None if response.tangent is None else np.array(response.tangent)
        if tangent is not None:
            tangent[list(BROKEN)] = np.nan
        return new, CellResponse(moment, response.area, response.diagnostics, tangent)

    monkeypatch.setattr(AnnCell, "step", step)


def test_a_drained_run_that_fails_names_the_cells_and_the_certificate(monkeypatch):
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    programme = programmes.triaxial(2e5, 0.02, 1e-4, test="drained", iso_increment=5e-5)
    _break(monkeypatch, after=60)
    model = make_cell_model("ann", dim=3)
    with pytest.raises(driver.ControlError) as caught:
        driver.run(model, programme, mesostructure=meso, lebedev_order=11, n_spins=4, progress=False)
    message = str(caught.value)
    assert "\n" not in message
    assert "did not converge" in message or "no stiffness" in message
    assert "ANN diagnosis: non-finite step in 2 of 100 cells: 3 (n = (" in message and "), 7 (n = (" in message
    assert "model certified (worst 0.175 %)" in message and "run inside its envelope" in message


def test_without_failed_cells_the_diagnosis_says_so_and_names_the_envelope():
    model = make_cell_model("ann", dim=3)
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    state = model.init_state(meso, 4)
    for _ in range(20):
        state, _ = model.step(state, np.full((4, 3), 3e-4))
    outside = programmes.triaxial(5e7, 0.3, 1e-4, test="drained")
    line = model.control_diagnosis(state, np.full((4, 3), 1e-5), np.eye(3)[[0, 1, 2, 0]], outside, meso)
    assert line.startswith("ANN diagnosis: no cell of 4 failed its step or tangent over the last trial; model certified")
    assert "run outside its envelope (" in line and "\n" not in line


def test_a_kink_inside_the_increment_is_a_tangent_off_the_step():
    model = make_cell_model("ann", dim=3)
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    state = model.init_state(meso, 2)  # touching, force-free: the first increment closes the contacts
    d = np.array([[1e-4, 1e-4, 1e-4], [-1e-4, -1e-4, -1e-4]])
    failed = model.failed_cells(state, d)
    assert not failed["step"].any() and not failed["tangent"].any()
    state_loaded = state
    for _ in range(20):
        state_loaded, _ = model.step(state_loaded, np.full((2, 3), 3e-4))
    smooth = model.failed_cells(state_loaded, np.full((2, 3), 1e-6))
    assert not smooth["off"].any()  # a loaded cell under a small increment follows its tangent


def test_hmodel_triaxial_prints_the_diagnosis_on_one_line_with_exit_code_2(monkeypatch, tmp_path, capsys):
    _break(monkeypatch, after=60)
    argv = ["triaxial", "--backend", "ann", "--mesostructure", "hcell3d:alpha0=55", "--p0", "2e5", "--drained",
            "--eps-max", "0.02", "--increment", "1e-4", "--order", "11", "--spins", "4", "--out", str(tmp_path / "run"),
            "-q"]
    assert hmodel.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ANN diagnosis: non-finite step in 2 of 100 cells" in err
    assert "Traceback" not in err


def test_the_diagnosis_names_the_cells_that_the_equilibrium_corrections_left_unbalanced():
    meso = mesostructure_arg("hcell3d:alpha0=55").build(55.0)
    hybrid = AnnCell3D(make_cell_model("ann", dim=3).contact_law, 0.5, model=default_model_path(3),
                       equilibrium_corrections=1, equilibrium_tolerance=1e-14)  # one step cannot reach 1e-14
    state = hybrid.init_state(meso, 4)
    for _ in range(20):
        state, _ = hybrid.step(state, np.full((4, 3), 3e-4))
    d = np.array([[1e-4, -5e-5, -5e-5]] * 4)
    _, response = hybrid.step(state, d)
    ratio = hybrid.unbalanced_cells(state, d)
    assert np.count_nonzero(ratio > 1e-14) == response.diagnostics["n_unconverged"] > 0
    line = hybrid.control_diagnosis(state, d, np.eye(3)[[0, 1, 2, 0]], programmes.triaxial(2e5, 0.02, 1e-4), meso)
    unbalanced = int(response.diagnostics["n_unconverged"])
    assert f"force ratio above 1e-14 after K = 1 equilibrium corrections in {unbalanced} of 4 cells: " in line
    assert f", ratio {ratio[np.argmax(ratio > 1e-14)]:.2g})" in line and "\n" not in line
    assert make_cell_model("ann", dim=3).unbalanced_cells(state, d).max() == 0.0  # no corrections, nothing named
