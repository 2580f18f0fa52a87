"""The critical-state renewal (homogenization.material.critical_state): parameters checked, default path
untouched, loose and dense drained points converging towards one state, DEM and closed form agreeing."""

from __future__ import annotations

import numpy as np
import pytest

from homogenization.backends import make_cell_model
from homogenization.element_test import driver, programme as pg
from dataclasses import replace

from homogenization.material.critical_state import DEFAULTS, CriticalState
from homogenization.material.density import default_map
from warp_hcell.mesostructures.hcell import plain_h_cell



@pytest.mark.parametrize("changes", [{"rate": 0.0}, {"rate": float("nan")}, {"gain": -1.0}, {"rate_gain": -0.5},
                                     {"rate_max": 10.0}, {"alpha_c_deg": 63.0},
                                     {"alpha_min_deg": 60.0, "alpha_max_deg": 50.0}, {"alpha_max_deg": 95.0},
                                     {"phases": "spin"}, {"rate_gain_loose": -1.0}])
def test_bad_parameters_are_refused(changes):
    params = CriticalState(**changes)
    with pytest.raises(ValueError, match="critical-state"):
        params.check()
    with pytest.raises(ValueError, match="critical-state"):
        driver.run(make_cell_model("analytical"), pg.biaxial(2e5, 0.01, 1e-3, drained=True),
                   mesostructure=plain_h_cell(2, 52.0), n_orientations=6, progress=False, critical_state=params)


def test_3d_fresh_cells_above_the_smallest_opening():
    with pytest.raises(ValueError, match="smallest opening"):
        driver.run(make_cell_model("analytical", dim=3), pg.triaxial(1e5, 0.01, 1e-3, test="drained"),
                   mesostructure=plain_h_cell(3, 52.0), lebedev_order=3, n_spins=1, progress=False,
                   critical_state=CriticalState(alpha_min_deg=40.0))


def test_default_run_is_the_plain_model():
    """Without the rule no renewal diagnostic and the same curve as a run that never renews (rate tiny)."""
    prog = pg.biaxial(2e5, 0.05, 1e-3, drained=True)
    args = dict(mesostructure=plain_h_cell(2, 52.0), n_orientations=12, progress=False)
    plain = driver.run(make_cell_model("analytical"), prog, **args)
    idle = driver.run(make_cell_model("analytical"), prog, critical_state=CriticalState(rate=1e-9, rate_gain=0.0),
                      **args)
    assert "critical_state_renewals" not in plain.diagnostics
    assert np.nanmax(idle.diagnostics["critical_state_renewals"]) == 0
    np.testing.assert_array_equal(plain.q, idle.q)
    np.testing.assert_array_equal(plain.J, idle.J)
    busy = driver.run(make_cell_model("analytical"), prog, critical_state=DEFAULTS[2], **args)
    assert np.nanmax(busy.diagnostics["critical_state_renewals"]) > 10
    assert np.max(np.abs(busy.q - plain.q)) > 0.01 * 2e5


def test_renewal_keeps_a_symmetric_planar_test_symmetric():
    """Mirror-image cells (theta, pi - theta) are renewed together: no macro shear stress appears."""
    rec = driver.run(make_cell_model("analytical"), pg.biaxial(2e5, 0.05, 1e-3, drained=True),
                     mesostructure=plain_h_cell(2, 52.0), n_orientations=36, progress=False,
                     critical_state=DEFAULTS[2])
    assert np.nanmax(rec.diagnostics["critical_state_renewals"]) > 50
    assert np.max(np.abs(rec.sigma12)) < 1e-9 * 2e5


def _end_void_ratio(alpha0: float, params: CriticalState | None) -> tuple[float, float]:
    rec = driver.run(make_cell_model("analytical", dim=3), pg.triaxial(1e5, 0.3, 4e-3, test="drained"),
                     mesostructure=plain_h_cell(3, alpha0), lebedev_order=11, n_spins=4, progress=False,
                     critical_state=params)
    e0 = default_map(3).void_ratio(alpha0)
    return (1.0 + e0) * rec.J[-1] - 1.0, rec.q[-1] / rec.p[-1]


def test_loose_and_dense_3d_points_meet():
    """Drained to 30 %: with the rule the void ratios of a dense and a loose point end within 0.02 (0.37 apart
    at the start) and their stress ratios within 10 %; the plain cell's stay 0.15 or more apart."""
    dense, loose = _end_void_ratio(48.0, DEFAULTS[3]), _end_void_ratio(56.0, DEFAULTS[3])
    assert abs(dense[0] - loose[0]) < 0.02
    assert abs(dense[1] / loose[1] - 1.0) < 0.10
    plain_dense, plain_loose = _end_void_ratio(48.0, None), _end_void_ratio(56.0, None)
    assert abs(plain_dense[0] - plain_loose[0]) > 0.15



def _end_2d(alpha0: float, params: CriticalState | None) -> tuple[float, float]:
    rec = driver.run(make_cell_model("analytical"), pg.biaxial(1e5, 0.4, 4e-3, drained=True),
                     mesostructure=plain_h_cell(2, alpha0), n_orientations=90, progress=False, critical_state=params)
    e0 = default_map(2).void_ratio(alpha0)
    return (1.0 + e0) * rec.J[-1] - 1.0, rec.q[-1] / rec.p[-1]


def test_loose_and_dense_2d_points_meet():
    """Drained biaxial to 40 % (90 orientations): with the rule the void ratios of a dense and a loose point end
    within 0.01 (0.19 apart at the start) and their stress ratios within 5 %; the plain cell's stay 0.1 apart and
    soften below q/p = 0.5."""
    dense, loose = _end_2d(48.0, DEFAULTS[2]), _end_2d(56.0, DEFAULTS[2])
    assert abs(dense[0] - loose[0]) < 0.01
    assert abs(dense[1] / loose[1] - 1.0) < 0.05
    plain_dense, plain_loose = _end_2d(48.0, None), _end_2d(56.0, None)
    assert abs(plain_dense[0] - plain_loose[0]) > 0.1
    assert max(plain_dense[1], plain_loose[1]) < 0.5


def test_dem_agrees_with_the_closed_form_under_renewal():
    params = replace(DEFAULTS[2], rate=400.0)
    p0 = 2e5
    prog = pg.biaxial(p0, 0.01, 1e-3, drained=True)
    records = [driver.run(make_cell_model(backend), prog, mesostructure=plain_h_cell(2, 52.0), n_orientations=12,
                          progress=False, critical_state=params) for backend in ("analytical", "dem")]
    a, d = records
    assert np.nanmax(a.diagnostics["critical_state_renewals"]) >= 10
    np.testing.assert_array_equal(a.diagnostics["critical_state_renewals"], d.diagnostics["critical_state_renewals"])
    assert max(np.max(np.abs(a.sigma11 - d.sigma11)), np.max(np.abs(a.sigma22 - d.sigma22))) < 1e-3 * p0


def test_dem_agrees_with_the_closed_form_under_renewal_3d():
    p0 = 1e5
    prog = pg.triaxial(p0, 0.01, 1e-3, test="drained")
    records = [driver.run(make_cell_model(backend, dim=3), prog, mesostructure=plain_h_cell(3, 52.0), lebedev_order=5,
                          n_spins=4, progress=False, critical_state=replace(DEFAULTS[3], rate=400.0))
               for backend in ("analytical", "dem")]
    a, d = records
    assert np.nanmax(a.diagnostics["critical_state_renewals"]) >= 20
    np.testing.assert_array_equal(a.diagnostics["critical_state_renewals"], d.diagnostics["critical_state_renewals"])
    assert max(np.max(np.abs(getattr(a, c) - getattr(d, c))) for c in ("sigma11", "sigma22", "sigma33")) < 1e-3 * p0


EARLIER = {dim: replace(DEFAULTS[dim], rate_max=400.0, rate_gain_loose=None, in_increment=False) for dim in (2, 3)}
"""The first version of the rule: renewed force-free after the increment, rate capped at 400."""


def _end_2d_p(alpha0: float, params: CriticalState, drained: bool, p0: float = 1e5,
              increment: float = 4e-3) -> tuple[float, float]:
    rec = driver.run(make_cell_model("analytical"), pg.biaxial(p0, 0.4, increment, drained=drained),
                     mesostructure=plain_h_cell(2, alpha0), n_orientations=90, progress=False, critical_state=params)
    e0 = default_map(2).void_ratio(alpha0)
    return float(rec.p[-1]), (1.0 + e0) * rec.J[-1] - 1.0


def test_loose_undrained_2d_point_ends_on_the_drained_line():
    """Undrained from the loose drained state (56 deg) and from alpha_c + 2 deg to 40 % (90 orientations): with the
    renewals made inside the increment they end within 0.02 in e of the line through the drained ends; renewed
    force-free after the increment (the earlier rule) the loose one ends more than 0.03 off."""
    ends = [_end_2d_p(a, DEFAULTS[2], True, p0) for a in (48.0, 56.0) for p0 in (1e5, 4e5)]
    lam, e_g = np.polyfit(-np.log([p for p, _ in ends]), [e for _, e in ends], 1)
    for alpha0 in (54.0, 56.0):
        p, e = _end_2d_p(alpha0, DEFAULTS[2], False)
        assert abs(e - (e_g - lam * np.log(p))) < 0.02
    p_old, e_old = _end_2d_p(56.0, EARLIER[2], False)
    assert e_old - (e_g - lam * np.log(p_old)) > 0.03


def test_undrained_end_converges_with_the_increment():
    """The loose undrained point renews every cell in every increment; its end p changes by less than 3 % from
    increments 4e-3 to 2e-3 with the renewals inside the increment, by more than 15 % without."""
    fine, coarse = (_end_2d_p(56.0, DEFAULTS[2], False, increment=h)[0] for h in (2e-3, 4e-3))
    assert abs(coarse / fine - 1.0) < 0.03
    fine, coarse = (_end_2d_p(56.0, EARLIER[2], False, increment=h)[0] for h in (2e-3, 4e-3))
    assert abs(coarse / fine - 1.0) > 0.15


def _end_3d_p(alpha0: float, params: CriticalState, test: str, p0: float = 1e5) -> tuple[float, float]:
    rec = driver.run(make_cell_model("analytical", dim=3), pg.triaxial(p0, 0.4, 4e-3, test=test),
                     mesostructure=plain_h_cell(3, alpha0), lebedev_order=11, n_spins=4, progress=False,
                     critical_state=params)
    e0 = default_map(3).void_ratio(alpha0)
    return float(rec.p[-1]), (1.0 + e0) * rec.J[-1] - 1.0


def test_loose_undrained_3d_point_ends_on_the_drained_line():
    """As the 2D test, triaxial (Lebedev 11 x 4 spins): the loose undrained point ends within 0.02 in e of the line
    through the drained ends, more than 0.03 off with the earlier rule."""
    ends = [_end_3d_p(a, DEFAULTS[3], "drained", p0) for a in (48.0, 56.0) for p0 in (1e5, 4e5)]
    lam, e_g = np.polyfit(-np.log([p for p, _ in ends]), [e for _, e in ends], 1)
    p, e = _end_3d_p(56.0, DEFAULTS[3], "undrained")
    assert abs(e - (e_g - lam * np.log(p))) < 0.02
    p_old, e_old = _end_3d_p(56.0, EARLIER[3], "undrained")
    assert e_old - (e_g - lam * np.log(p_old)) > 0.03
