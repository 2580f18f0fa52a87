"""The 3D cell kind that liquefies (hcell3d-axisym, docs/model.md section 14): its kinematics, its
builder, and static liquefaction of the loose cell against dilation of the dense one on the
undrained triaxial path (closed form and DEM), next to the ten-sphere cell with projected kinematics
that does not liquefy (docs/triaxial.md, Static liquefaction in 3D)."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from homogenization.element_test import driver, programme as programmes
from homogenization.backends import make_cell_model
from homogenization.backends.analytical import Analytical3DCell
from homogenization.material.orientation import localise
from homogenization.material.orientation import AXISYMMETRIC_MAP, cell_kinematics, orientations_3d
from warp_hcell.mesostructures.builders import resolve_mesostructure

P0 = 2e5
LOOSE, DENSE = 54.0, 49.0
"""The documented loose and dense opening angles of hcell3d-axisym [deg]."""
TOUCHING = 47.0
"""A denser cell whose planes' lateral grains meet within 15 % (from 8.9 %), where the closed form stops holding [deg]."""


def test_axisymmetric_kinematics_keep_isotropic_increments_and_make_every_plane_isochoric():
    projected = orientations_3d(11, 4)
    axisym = orientations_3d(11, 4, kinematics="axisymmetric")
    iso = np.array([1e-3, 1e-3, 1e-3, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(localise(axisym, iso), localise(projected, iso), rtol=0, atol=1e-18)
    d = np.array([1e-3, -0.5e-3, -0.5e-3, 0.0, 0.0, 0.0])  # isochoric to first order
    old, new = localise(projected, d), localise(axisym, d)
    # projected: planes containing the axial direction are compressed by up to half the axial strain
    assert (old[:, 0] + old[:, 1]).max() > 0.4e-3
    # axisymmetric: every plane (n, t1) and (n, t2) keeps its area (to first order, as d does), t1 and t2 alike
    assert np.abs(new[:, 0] + new[:, 1]).max() < 1e-18 and np.abs(new[:, 0] + new[:, 2]).max() < 1e-18
    np.testing.assert_array_equal(new[:, 1], new[:, 2])
    # the plane keeps the cell's axisymmetric deviator d_eps_n - (d_eps_t1 + d_eps_t2)/2
    np.testing.assert_allclose(new[:, 0] - new[:, 1], old[:, 0] - 0.5 * (old[:, 1] + old[:, 2]), atol=1e-15)
    np.testing.assert_allclose(AXISYMMETRIC_MAP.sum(axis=1), 1.0, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="kinematics"):
        orientations_3d(5, 1, kinematics="axial")


def test_builder_declares_the_kinematics_and_the_closed_form_accepts_the_cell():
    axisym = resolve_mesostructure(f"hcell3d-axisym:alpha0={LOOSE:g}")
    plain = resolve_mesostructure(f"hcell3d:alpha0={LOOSE:g}")
    assert cell_kinematics(axisym) == "axisymmetric" and cell_kinematics(plain) == "projected"
    np.testing.assert_array_equal(axisym.position, plain.position)
    assert Analytical3DCell.check_mesostructure(axisym) == LOOSE


def run(spec: str, backend: str = "analytical", *, eps_max: float = 0.15, increment: float = 1e-3,
        order: int = 11, spins: int = 1) -> driver.Record:
    programme = programmes.triaxial(P0, eps_max, increment, test="undrained", iso_increment=1e-4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an unconverged DEM cell fails the test
        return driver.run(make_cell_model(backend, dim=3), programme, mesostructure=resolve_mesostructure(spec),
                          lebedev_order=order, n_spins=spins, progress=False)


def shear_p(record: driver.Record) -> tuple[np.ndarray, np.ndarray]:
    """(axial strain of the shear stage [-], p / p0 [-])."""
    shear = record.stage == "shear"
    start = record.eps11[~shear][-1]
    return record.eps11[shear] - start, record.p[shear] / P0


def test_loose_cell_liquefies_and_dense_cell_dilates_in_undrained_triaxial_compression():
    """The loose cell's liquefaction onset, the first axial strain with p < 0.3 p0, lies within [7.0, 8.5] %:
    measured 7.6 % on this rule (25 axes, increment 1e-3), 7.3-8.1 % on 7 to 487 axes at 1e-3 or 1e-4
    (8.1 %: docs/triaxial.md's rule); alpha0 = 53.5 deg gives 6.5 %, 53 deg 10.7 %, 55 deg 14.7 %, 52 and
    56 deg never. The dense cell and the projected kinematics do not liquefy."""
    # 25 axes x 1 spin: with these kinematics a cell's response does not depend on its spin
    eps, p = shear_p(run(f"hcell3d-axisym:alpha0={LOOSE:g}"))
    below = np.flatnonzero(p < 0.3)
    onset = eps[below[0]] if below.size else None
    assert onset is not None and 0.070 <= onset <= 0.085, f"p < 0.3 p0 from {onset} (lowest {p.min():.3f} p0)"
    eps, p = shear_p(run(f"hcell3d-axisym:alpha0={DENSE:g}"))
    assert p.min() > 0.95 and p[np.argmin(np.abs(eps - 0.10))] > 2.5  # measured: lowest 0.994, 3.47 at 10 %
    eps, p = shear_p(run(f"hcell3d:alpha0={LOOSE:g}", eps_max=0.05))
    assert p[-1] > 5.0  # projected kinematics, same grains: no liquefaction (measured 9.5 at 5 %)


@pytest.mark.parametrize(("alpha0", "p_tolerance"), [(LOOSE, 1e-4), (DENSE, 2e-4)])
def test_dem_follows_the_closed_form_to_15_percent_on_the_loose_and_the_dense_cell(alpha0, p_tolerance):
    """The acceptance of the cell (docs/triaxial.md, DEM against the closed form) on 25 cells at increment 1e-3:
    no lateral grains of the two planes meet (the closed form's count), and the DEM is within 1e-3 of p0."""
    spec = f"hcell3d-axisym:alpha0={alpha0:g}"
    closed, dem = run(spec), run(spec, "dem")
    shear = closed.stage == "shear"
    assert np.max(closed.diagnostics["n_cross_plane"]) == 0
    assert np.abs(dem.p - closed.p)[shear].max() < p_tolerance * P0  # measured 2.5e-5 (loose), 5.8e-5 (dense)
    assert np.abs(dem.q - closed.q)[shear].max() < 1e-3 * P0  # measured 3.3e-4, 6.9e-4


def test_the_closed_form_counts_the_cells_where_it_stops_holding():
    """At 47 deg the planes' lateral grains meet from 8.9 %: the DEM follows the closed form until the closed form
    counts the first such cell, then models contacts that the closed form leaves out."""
    spec = f"hcell3d-axisym:alpha0={TOUCHING:g}"
    closed, dem = run(spec), run(spec, "dem")
    shear = closed.stage == "shear"
    cross = np.asarray(closed.diagnostics["n_cross_plane"])[shear]
    first = np.argmax(cross > 0)
    eps, _ = shear_p(closed)
    assert cross.max() > 0 and 0.05 < eps[first] < 0.12  # measured 4 cells of 25 from 8.9 %, 12 at 15 %
    gap = np.abs(dem.p - closed.p)[shear] / P0
    assert gap[:first].max() < 1.5e-4 and gap[-1] > 1.0  # measured 3.7e-5 before, 9.5 p0 at 15 %


def test_the_shipped_meso_ann_is_not_certified_for_these_kinematics():
    model = make_cell_model("ann", dim=3)
    model.init_state(resolve_mesostructure("hcell3d:alpha0=55"), 1)
    assert model.certificate_problem is None  # the cell and the kinematics its certificate was measured on
    model.init_state(resolve_mesostructure("hcell3d-axisym:alpha0=55"), 1)  # same grains, same start state
    assert "projected kinematics" in model.certificate_problem


def test_the_yade_cases_of_the_cell_follow_its_kinematics():
    """tests/yade/make_reference3d.py writes the axisym cases' cell strains without the package."""
    spec = importlib.util.spec_from_file_location("make_reference3d", Path(__file__).parent / "yade" / "make_reference3d.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    for step in ((2e-4, -1e-4, -1e-4), (-1e-4, 2e-4, -1e-4), (3e-4, -5e-5, 1e-4)):
        np.testing.assert_allclose(module.axisymmetric(step), AXISYMMETRIC_MAP @ np.array(step), rtol=0, atol=1e-19)
    assert {"axisym3d_a54_axial", "axisym3d_a54_normal"} <= set(module.CASES)
