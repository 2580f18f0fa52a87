"""Orientation sets of both dimensions: frames and weights, localisation (spec section 3), rotation and
averaging (sections 7-8); the planar rule's angles and fabric, the 3D rule's Lebedev axes and spins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from homogenization.material import orientation
from homogenization.material.orientation import (
    SPIN_STAGGER,
    average_moment,
    hemisphere_rule,
    localise,
    orientations_3d,
    volume_ratio_factor,
)
from homogenization.backends import make_cell_model
from warp_hcell.core.dimension import dimension
from warp_hcell.mesostructures.hcell import h_cell

RULES = {2: [lambda: orientation.orientations(7), lambda: orientation.orientations(12, anisotropy=0.3, direction_deg=20.0)],
         3: [lambda: orientations_3d(5, 1), lambda: orientations_3d(11, 4), lambda: orientations_3d(17, 3)]}
"""Orientation sets checked in each dimension."""
RULE_CASES = [pytest.param(dim, rule, id=f"{dim}D-{k}") for dim, rules in RULES.items() for k, rule in enumerate(rules)]


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


@pytest.mark.parametrize("dim, rule", RULE_CASES)
def test_frames_are_rotations_with_weights_summing_to_one(dim, rule):
    orient = rule()
    assert orient.frames.shape == (orient.n_cells, dim, dim)
    eye = np.einsum("kai,kaj->kij", orient.frames, orient.frames)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(dim), eye.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(orient.frames), 1.0, atol=1e-14)
    assert np.isclose(orient.weights.sum(), 1.0)
    np.testing.assert_array_equal(orient.axes, orient.frames[:, :, 0])


@pytest.mark.parametrize("dim, rule", RULE_CASES)
def test_localisation_projects_the_strain_on_each_cell_axis(dim, rule):
    orient, space = rule(), dimension(dim)
    d_eps = np.random.default_rng(0).normal(size=space.n_voigt)
    expected = np.einsum("kia,ij,kja->ka", orient.frames, space.to_tensor(d_eps), orient.frames)
    np.testing.assert_allclose(localise(orient, d_eps), expected, atol=1e-14)


@pytest.mark.parametrize("dim, rule", RULE_CASES)
def test_averaging_rotates_the_moments_to_the_macro_frame(dim, rule):
    orient, space = rule(), dimension(dim)
    moment = np.random.default_rng(1).normal(size=(orient.n_cells, dim, dim))
    moment = moment + moment.transpose(0, 2, 1)
    expected = np.einsum("k,kia,kab,kjb->ij", orient.weights, orient.frames, moment, orient.frames)
    np.testing.assert_allclose(space.to_tensor(average_moment(orient, moment)), expected, atol=1e-13)


@pytest.mark.parametrize("dim, orient", [(2, orientation.orientations(4)), (3, orientations_3d(5, 1))], ids=["2D", "3D"])
def test_an_axial_cell_averages_to_an_isotropic_tensor(dim, orient):
    """<n n> = I / d over the circle (from 2 angles) or the sphere (exact from order 3)."""
    moment = np.zeros((orient.n_cells, dim, dim))
    moment[:, 0, 0] = 1.0
    np.testing.assert_allclose(dimension(dim).to_tensor(average_moment(orient, moment)), np.eye(dim) / dim, atol=1e-14)


def test_the_lebedev_hemisphere_keeps_one_of_each_antipodal_pair():
    axes, weights = hemisphere_rule(11)
    assert axes.shape == (25, 3)
    assert np.isclose(weights.sum(), 1.0)
    dots = axes @ axes.T
    assert not np.any(np.isclose(dots - np.eye(25), -1.0))
    with pytest.raises(ValueError, match="Lebedev order 4"):
        hemisphere_rule(4)


@pytest.mark.parametrize("dim, orient", [(2, orientation.orientations(8)), (3, orientations_3d(7, 2)),
                                         (3, orientations_3d(11, 4))], ids=["2D", "3D-7x2", "3D-11x4"])
def test_cells_that_respond_along_their_axes_give_an_isotropic_material(dim, orient):
    """A cell with S = diag(k_n eps_n, k_t eps_t...) gives a macro stiffness of the isotropic form
    lambda tr(eps) I + 2 G eps: fourth moments of n are exact on the circle from 3 angles and on the
    sphere from order 5, and the lateral axes of a 3D cell average isotropically for >= 2 spins over 90 deg."""
    space = dimension(dim)
    k = np.array([3.0] + [1.0] * (dim - 1))

    def stress(d_eps):
        moment = np.zeros((orient.n_cells, dim, dim))
        moment[:, np.arange(dim), np.arange(dim)] = k * localise(orient, d_eps)
        return average_moment(orient, moment)

    columns = np.stack([stress(np.eye(space.n_voigt)[m]) for m in range(space.n_voigt)], axis=1)
    lam, two_g = columns[1, 0], columns[0, 0] - columns[1, 0]
    isotropic = np.zeros((space.n_voigt, space.n_voigt))
    isotropic[:dim, :dim] = lam
    isotropic[np.arange(space.n_voigt), np.arange(space.n_voigt)] += two_g
    np.testing.assert_allclose(columns, isotropic, atol=1e-12)
    assert two_g > 0


@pytest.mark.parametrize("d_eps, factor", [([0.1, -0.2, 9.0], 0.9 * 1.2), ([0.1, -0.2, 0.3, 9.0, 9.0, 9.0], 0.9 * 1.2 * 0.7)],
                         ids=["2D", "3D"])
def test_volume_ratio_factor_multiplies_the_normal_stretches(d_eps, factor):
    assert volume_ratio_factor(np.array(d_eps)) == pytest.approx(factor)


def test_staggered_spins_sample_distinct_phases_and_keep_each_axis_equally_spaced():
    """Staggering (the default) gives every axis its own spin phase, frac(k g) of a spin step; each
    axis keeps n equally spaced spins over the period, so the isotropy of the rule is kept."""
    aligned, staggered = orientations_3d(11, 4, staggered=False), orientations_3d(11, 4)
    assert staggered.staggered and not aligned.staggered
    np.testing.assert_array_equal(aligned.frames[:, :, 0], staggered.frames[:, :, 0])  # the same axes
    np.testing.assert_array_equal(aligned.weights, staggered.weights)
    step = np.radians(90.0) / 4
    a, b = aligned.frames.reshape(25, 4, 3, 3), staggered.frames.reshape(25, 4, 3, 3)
    psi = np.arctan2(np.einsum("ksi,ksi->ks", b[..., 1], a[:, :1, :, 2]), np.einsum("ksi,ksi->ks", b[..., 1], a[:, :1, :, 1]))
    expected = step * (np.arange(4)[None, :] + ((np.arange(25) * SPIN_STAGGER) % 1.0)[:, None])
    np.testing.assert_allclose(psi, expected, atol=1e-12)
    assert np.unique(np.round(psi[:, 0] / step, 9)).size == 25  # 25 distinct phases, not one
