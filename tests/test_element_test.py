"""The element-test engine: a run continues from the points' state, a point's curve does not depend on its
batch under either policy, the policies differ only where they say, and every caller orients cells alike."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from homogenization.element_test import programme as programmes
from homogenization.backends.analytical import AnalyticalCell
from homogenization.element_test.points import material_points, orientation_set
from homogenization.element_test.record import History
from homogenization.element_test.stages import run_stages
from homogenization.element_test.solver import POPULATION, STRICT, ControlError, StressControl
from warp_hcell.mesostructures.builders import resolve_mesostructure
from warp_hcell.mesostructures.hcell import h_cell

P0 = 3e6
PROGRAMME = programmes.biaxial(P0, 0.01, 1e-3, iso_increment=1e-3, drained=True)
LAWS = {"kn": [2e8, 5e8, 1e8], "kt_over_kn": [0.5, 0.9, 0.3], "phi_g": [30.0, 20.0, 40.0], "alpha0": [55.0, 65.0, 45.0]}
N_ORIENTATIONS = 12


def points_of(sets: list[int]):
    """Material points of the parameter sets ``sets`` of ``LAWS``, one per point."""
    per_cell = {k: np.repeat(np.array(v)[sets], N_ORIENTATIONS) for k, v in LAWS.items()}
    model = AnalyticalCell.with_cell_laws(per_cell["kn"], per_cell["kt_over_kn"], per_cell["phi_g"], 0.5,
                                          alpha0_deg=per_cell["alpha0"])
    return material_points(model, h_cell(55.0, 0.5), len(sets), n_orientations=N_ORIENTATIONS,
                           lebedev_order=11, n_spins=1)


def history_of(points, stages, policy=STRICT) -> History:
    history = History(sum(s.n_increments for s in stages), points.n, points.dim, observe=False)
    run_stages(StressControl(points, policy), stages, history)
    return history


def test_a_run_goes_on_from_the_state_it_was_left_in():
    whole = history_of(points_of([0]), PROGRAMME)
    points = points_of([0])
    first = history_of(points, PROGRAMME[:1])
    second = history_of(points, PROGRAMME[1:])
    joined = np.concatenate([first.rows[:first.k], second.rows[:second.k]])
    assert joined.tobytes() == whole.rows[:whole.k].tobytes()
    assert abs(whole.rows[whole.k - 1, 0, 3] - P0) <= STRICT.rtol * P0  # sigma22 held at p0


@pytest.mark.parametrize("policy", [STRICT, POPULATION], ids=["strict", "population"])
def test_a_point_does_not_depend_on_its_batch(policy):
    """To rounding: the analytical cells' own equilibrium iterations run as long as the batch's slowest cell."""
    batch = history_of(points_of([0, 1, 2]), PROGRAMME, policy)
    for i in range(3):
        alone = history_of(points_of([i]), PROGRAMME, policy)
        # the isotropic stage of a batch lasts until its last point lands; the others wait at p0
        n_iso = int((alone.stage_index[:alone.k] == 0).sum())
        shear_batch = batch.rows[:batch.k][batch.stage_index[:batch.k] == 1, i]
        shear_alone = alone.rows[:alone.k][alone.stage_index[:alone.k] == 1, 0]
        scale = np.array([1.0, 1.0, P0, P0, P0, 1.0])  # eps11, eps22 [-], sigma11, sigma22, sigma12 [N/m], J [-]
        np.testing.assert_allclose(shear_batch / scale, shear_alone / scale, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(batch.rows[n_iso - 1, i] / scale, alone.rows[n_iso - 1, 0] / scale, rtol=1e-12,
                                   atol=1e-15)


def test_the_strict_policy_raises_where_the_population_counts():
    tight = replace(STRICT, max_iterations=1, rtol=1e-12)
    with pytest.raises(ControlError, match="step 'iso', increment [0-9]+: could not land p on 3e.06 N/m in 1 step calls"):
        history_of(points_of([0]), PROGRAMME, tight)
    points = points_of([0, 1])
    history = History(sum(s.n_increments for s in PROGRAMME), 2, 2, observe=False)
    _, fallback, unreached = run_stages(StressControl(points, replace(POPULATION, max_iterations=1, rtol=1e-12)), PROGRAMME,
                                        history)
    n_shear = PROGRAMME[1].n_increments
    assert np.all(fallback >= n_shear) and not unreached.any()  # every shear increment took its one iterate


def test_every_caller_orients_a_cell_by_its_own_kinematics():
    axisym = resolve_mesostructure("hcell3d-axisym")
    plain = resolve_mesostructure("hcell3d")
    options = dict(n_orientations=1, lebedev_order=11, n_spins=2, staggered_spins=False)
    assert orientation_set(axisym, **options).kinematics == "axisymmetric"
    assert orientation_set(plain, **options).kinematics == "projected"
