"""Orientations: weights, localisation (spec section 3), rotation and averaging (sections 7-8)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from homogenization.material import orientation
from homogenization.backends import make_cell_model
from warp_hcell.mesostructures.hcell import h_cell


def test_angles_and_isotropic_weights():
    orient = orientation.orientations(360)
    assert orient.theta[1] == pytest.approx(math.pi / 360) and orient.theta[-1] == pytest.approx(359 * math.pi / 360)
    assert np.all(orient.weights == 1.0 / 360)


def test_fabric_weights_follow_w_theta():
    orient = orientation.orientations(8, anisotropy=0.4, direction_deg=30.0)
    expected = (1 + 0.4 * np.cos(2 * (np.arange(8) * math.pi / 8 - math.pi / 6))) / 8
    assert orient.weights == pytest.approx(expected, rel=1e-14)
    assert orient.weights.sum() == pytest.approx(1.0, rel=1e-14)
    with pytest.raises(ValueError, match=r"^fabric anisotropy = 1 is outside \[0, 1\)$"):
        orientation.orientations(8, anisotropy=1.0)


def test_localisation_projects_on_n_and_t():
    orient = orientation.orientations(7)
    d_eps = np.array([2e-3, -1e-3, 5e-4])  # (11, 22, 12), tensor components
    tensor = np.array([[d_eps[0], d_eps[2]], [d_eps[2], d_eps[1]]])
    local = orientation.localise(orient, d_eps)
    for k, th in enumerate(orient.theta):
        n = np.array([math.cos(th), math.sin(th)])
        t = np.array([-math.sin(th), math.cos(th)])
        assert local[k] == pytest.approx([n @ tensor @ n, t @ tensor @ t], rel=1e-13, abs=1e-19)


def test_isotropic_strain_gives_equal_local_strains():
    local = orientation.localise(orientation.orientations(360), np.array([1e-5, 1e-5, 0.0]))
    assert np.abs(local - 1e-5).max() <= 1e-20


def test_average_moment_rotates_local_tensors():
    rng = np.random.default_rng(0)
    orient = orientation.orientations(5, anisotropy=0.3, direction_deg=10.0)
    moment = rng.normal(size=(5, 2, 2))
    expected = np.zeros((2, 2))
    for k, th in enumerate(orient.theta):
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])  # columns n, t
        expected += orient.weights[k] * R @ moment[k] @ R.T
    sym12 = 0.5 * (expected[0, 1] + expected[1, 0])
    assert orientation.average_moment(orient, moment) == pytest.approx([expected[0, 0], expected[1, 1], sym12], rel=1e-12)


def test_spec_rotation_formula_for_symmetric_cells():
    # spec section 7: S11 = Snn c^2 + Stt s^2, S22 = Snn s^2 + Stt c^2, S12 = (Snn - Stt) s c.
    orient = orientation.orientations(4)
    c, s = math.cos(orient.theta[1]), math.sin(orient.theta[1])
    moment = np.zeros((4, 2, 2))
    moment[1] = [[3.0, 0.0], [0.0, 1.0]]
    out = orientation.average_moment(orient, moment) * 4
    assert out == pytest.approx([3 * c * c + s * s, 3 * s * s + c * c, (3 - 1) * s * c], rel=1e-14)


def test_theta_and_theta_plus_pi_give_the_same_cell():
    # n(theta + pi) = -n(theta), t(theta + pi) = -t(theta): same local strains, same macro moment.
    orient = orientation.orientations(6)
    d_eps = np.array([1e-3, -4e-4, 2e-4])
    tensor = np.array([[d_eps[0], d_eps[2]], [d_eps[2], d_eps[1]]])
    local = orientation.localise(orient, d_eps)
    cell = make_cell_model("analytical")
    state = cell.init_state(h_cell(55.0), 6)
    _, response = cell.step(state, local)
    macro = np.zeros((2, 2))
    for k, th in enumerate(orient.theta + math.pi):
        n = np.array([math.cos(th), math.sin(th)])
        t = np.array([-math.sin(th), math.cos(th)])
        assert local[k] == pytest.approx([n @ tensor @ n, t @ tensor @ t], rel=1e-12)
        R = np.stack([n, t], axis=1)
        macro += orient.weights[k] * R @ response.moment[k] @ R.T
    assert orientation.average_moment(orient, response.moment) == pytest.approx(
        [macro[0, 0], macro[1, 1], macro[0, 1]], rel=1e-12, abs=1e-9 * np.abs(macro).max())


def test_initial_volume_and_J_factor():
    orient = orientation.orientations(4, anisotropy=0.5)
    area = np.array([1.0, 2.0, 3.0, 4.0])
    assert orientation.initial_volume(orient, area) == pytest.approx(float(orient.weights @ area))
    assert orientation.volume_ratio_factor(np.array([1e-3, -1e-3, 0.0])) == pytest.approx(1 - 1e-6, rel=1e-15)
    assert "V = V0*J" in orientation.VOLUME_RULE and "hexagon" in orientation.VOLUME_RULE
