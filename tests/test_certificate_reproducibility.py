"""The DEM's own reproducibility in the certificate: a DEM state at rest (``DemCell.at_rest``), the DEM
stepped from rest in every increment (``homogenization.learning.from_rest.FromRest``) and each test's
``dem_spread`` (reported only: the verdict is that of the ANN against the DEM)."""

import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from homogenization.ann import default_model_path
from homogenization.element_test import driver, programme as programmes
from homogenization.learning import certificate
from homogenization.learning.from_rest import FromRest
from warp_hcell.core.parameters import ContactLaw, DemSettings
from warp_hcell.dem.cell import DemCell, DemCellState
from warp_hcell.dem.state import DemState
from warp_hcell.mesostructures.builders import mesostructure_arg

SHIPPED_3D = default_model_path(3)
needs_model = pytest.mark.skipif(not SHIPPED_3D.is_file(), reason="3D model not installed")

TINY = {"pressures": (2e5,), "eps_max": 0.01, "spatial_rule": (3, 1), "rollout": False}
"""A tiny 3D certificate of the plain ten-sphere cell of the shipped model: 1 % strain, 3 cells."""
PLAIN_SPREAD = 0.002
"""Bound of ``dem_spread`` on the plain cell's tiny certificates [-] (measured 0.007-0.109 % over its
five tests, 3 cells: no fine grain leaves a wedge, so the memory moves no drop)."""


def _sheared_cells() -> tuple[DemCell, DemCellState]:
    """Three plain 3D cells compressed and sheared by a few increments: a state with a velocity memory."""
    dem = DemCell(ContactLaw(), 0.5, threads=1)
    state = dem.init_state(mesostructure_arg("hcell3d:alpha0=52").build(None), 3)
    for d_eps in [np.full((3, 3), 1e-4)] * 3 + [np.tile([2e-4, -1e-4, -1e-4], (3, 1))] * 2:
        state, _ = dem.step(state, d_eps)
    return dem, state


def test_at_rest_zeroes_the_memory_and_leaves_its_argument_as_it_was():
    dem, state = _sheared_cells()
    before = {name: np.array(v) for name, v in state.dem.to_numpy().items()}
    assert np.abs(before["velocity"]).max() > 0
    rested = DemCell.at_rest(state)
    assert np.all(rested.dem.velocity.numpy() == 0)
    assert rested.model.settings.refined_strain_per_substep == DemSettings().rest_strain_per_substep
    assert state.model.settings.refined_strain_per_substep == DemSettings().refined_strain_per_substep
    assert DemCell.at_rest(rested).model is rested.model
    for name, values in state.dem.to_numpy().items():
        np.testing.assert_array_equal(values, before[name], err_msg=name)
        if name != "velocity":
            np.testing.assert_array_equal(rested.dem.to_numpy()[name], values, err_msg=name)


def test_from_rest_steps_as_the_dem_from_a_state_without_velocity_bit_for_bit():
    dem, state = _sheared_cells()
    arrays = {name: np.array(v) for name, v in state.dem.to_numpy().items()}
    arrays["velocity"][:] = 0.0
    rate = DemSettings().rest_strain_per_substep
    slow = DemCell(ContactLaw(), 0.5, settings=DemSettings(refined_strain_per_substep=rate), threads=1)
    without = slow.state_from_arrays({**dem.state_to_arrays(state), "velocity": arrays["velocity"]})
    d_eps = np.tile([2e-4, -1e-4, -1e-4], (3, 1))
    expected, _ = slow.step(without, d_eps)
    rested, _ = FromRest(dem).step(state, d_eps)
    remembered, _ = dem.step(state, d_eps)
    for name, values in expected.dem.to_numpy().items():
        np.testing.assert_array_equal(rested.dem.to_numpy()[name], values, err_msg=name)
    assert not np.array_equal(remembered.dem.substeps.numpy(), expected.dem.substeps.numpy())


LARGE_AXIAL = Path(__file__).parents[1] / "benchmarks" / "cells" / "large_axial.toml"
FOLLOWED_THROUGH_DROPS = 0.0015
"""Bound of the DEM from rest against the DEM on ``LARGE_AXIAL``'s drained compression [-] of the scale
(measured 0.032 % on these 7 cells; started from rest at the refined rate of 5e-6, 14.1 %: a fine grain
left its wedge one increment apart)."""


def test_the_dem_from_rest_follows_the_dem_where_fine_grains_leave_their_wedges():
    dem = DemCell(ContactLaw(), 0.5, threads=1)
    meso = mesostructure_arg(str(LARGE_AXIAL)).build(None)
    programme = programmes.triaxial(2e5, 0.10, 1e-4, test="drained", iso_increment=0.5e-4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d, r = (driver.run(model, programme, mesostructure=meso, lebedev_order=5, n_spins=1, progress=False)
                for model in (dem, FromRest(dem)))
    shear = d.stage != d.programme[0].label
    off = np.maximum(np.abs(r.p - d.p), np.abs(r.q - d.q))[shear] / max(2e5, d.p.max())
    assert off.max() < FOLLOWED_THROUGH_DROPS


def _copy(folder: Path) -> Path:
    folder.mkdir()
    for suffix in (".pt", ".json"):
        shutil.copy(SHIPPED_3D.with_suffix(suffix), folder / f"m{suffix}")
    return folder / "m.pt"


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    return _copy(tmp_path_factory.mktemp("reproducibility") / "m")


@needs_model
def test_every_test_reports_a_small_spread_on_the_plain_cell_and_the_verdict_is_that_without(tiny_model):
    cert = certificate.certify(tiny_model, **TINY)
    without = certificate.certify(tiny_model, **TINY, reproducibility=False)
    spreads = [t.dem_spread for t in cert.tests]
    assert all(math.isfinite(s) and 0 <= s < PLAIN_SPREAD for s in spreads), spreads
    assert cert.dem_spread == {"max": max(spreads), "test": cert.tests[int(np.argmax(spreads))].name,
                                  "above_target": []}
    assert without.dem_spread is None and all(t.dem_spread is None for t in without.tests)
    for key in ("worst", "worst_test", "within_target", "verdict", "passed"):
        assert getattr(cert, key) == getattr(without, key), key
    assert [(t.dp, t.dq) for t in cert.tests] == [(t.dp, t.dq) for t in without.tests]
    lines = certificate.summary_lines(cert)
    assert sum("DEM from rest off the DEM by" in line for line in lines) == len(cert.tests)
    assert not any("reproducibility" in line for line in lines)


@needs_model
def test_a_dem_from_rest_that_cannot_follow_is_reported_not_raised(tiny_model, monkeypatch):
    def refuse(self, state, d_eps_local, *, with_tangent=False):
        raise driver.ControlError("no convergence")

    monkeypatch.setattr(FromRest, "step", refuse)
    cert = certificate.certify(tiny_model, **{**TINY, "pressures": (1e6,)})
    assert all(t.dem_spread == math.inf and t.dem_spread_error == "no convergence" for t in cert.tests)
    assert cert.within_target and len(cert.dem_spread["above_target"]) == len(cert.tests)
    lines = certificate.summary_lines(cert)
    assert sum("(above the target)" in line for line in lines) == len(cert.tests)
    assert any(line.startswith(f"the DEM's own reproducibility: started from rest in every increment it moves "
                               f"{len(cert.tests)} test(s)") for line in lines)


@needs_model
def test_a_test_the_ann_cannot_follow_still_reports_the_spread(tiny_model, monkeypatch):
    def refuse(self, state, d_eps, *, with_tangent=False):
        raise driver.ControlError("no convergence")

    monkeypatch.setattr(certificate._Counter, "step", refuse)
    cert = certificate.certify(tiny_model, **TINY)
    assert all(t.dp == math.inf and t.error is not None for t in cert.tests)
    assert all(0 <= t.dem_spread < PLAIN_SPREAD for t in cert.tests)
