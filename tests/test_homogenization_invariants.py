"""Invariants p, q, t, eps_v and the second-order work W2 (spec section 9)."""

from __future__ import annotations

import numpy as np
import pytest

from homogenization.element_test import driver, programme as programmes
from homogenization.material import invariants
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell


def test_p_q_t_compression_positive():
    assert invariants.mean_stress(3.0e6, 1.0e6) == pytest.approx(2.0e6)
    assert invariants.deviator(3.0e6, 1.0e6) == pytest.approx(2.0e6)  # axial compression: q > 0
    assert invariants.deviator(1.0e6, 3.0e6) == pytest.approx(-2.0e6)
    assert invariants.volumetric_strain(0.02, -0.005) == pytest.approx(0.015)


def test_second_order_work_by_hand():
    s11, s22, s12 = np.array([0.0, 2.0, 3.0]), np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.5, 0.5])
    e11, e22, e12 = np.array([0.0, 0.1, 0.3]), np.array([0.0, -0.1, -0.2]), np.array([0.0, 0.2, 0.1])
    expected = [2.0 * 0.1 + 1.0 * -0.1 + 2 * 0.5 * 0.2, 1.0 * 0.2 + -1.0 * -0.1 + 0.0]
    assert invariants.second_order_work(s11, s22, s12, e11, e22, e12) == pytest.approx(expected)


def test_w2_changes_sign_at_the_q_peak():
    record = driver.run(make_cell_model("analytical"), programmes.biaxial(5.85e6, 0.08, 2e-4), mesostructure=h_cell(55.0),
                        n_orientations=72, progress=False)
    shear = np.flatnonzero(record.stage == "shear")
    k = np.concatenate([[shear[0] - 1], shear])  # include the end of the isotropic stage
    w2 = invariants.second_order_work(record.sigma11[k], record.sigma22[k], record.sigma12[k],
                                      record.eps11[k], record.eps22[k])
    # constant volume: W2 = dq d_eps11
    assert w2 == pytest.approx(np.diff(record.q[k]) * 2e-4, rel=1e-6, abs=1e-9 * record.p[k].max() * 2e-4)
    i_peak = int(np.argmax(record.q[k]))
    first_negative = int(np.flatnonzero(w2 < 0.0)[0])
    assert 0 < i_peak < len(k) - 1
    assert np.all(w2[:first_negative] > 0.0)
    assert abs(first_negative - i_peak) <= 1  # the increment right after the peak
