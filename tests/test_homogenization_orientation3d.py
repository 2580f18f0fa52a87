"""3D orientation sets: frames, weights, isotropy of the localisation and averaging."""

import numpy as np
import pytest

from homogenization.material.orientation import (
    average_moment,
    hemisphere_rule,
    localise,
    orientations_3d,
    volume_ratio_factor,
)
from warp_hcell.core.dimension import dimension

COMPONENTS = dimension(3).components
to_tensor = dimension(3).to_tensor


def test_hemisphere_keeps_one_point_of_each_antipodal_pair():
    axes, weights = hemisphere_rule(11)
    assert axes.shape == (25, 3)
    assert np.isclose(weights.sum(), 1.0)
    dots = axes @ axes.T
    assert not np.any(np.isclose(dots - np.eye(25), -1.0))
    with pytest.raises(ValueError, match="Lebedev order 4"):
        hemisphere_rule(4)


@pytest.mark.parametrize("order,n_spins", [(5, 1), (11, 4), (17, 3)])
def test_frames_are_rotations_with_weights_summing_to_one(order, n_spins):
    orient = orientations_3d(order, n_spins)
    eye = np.einsum("kai,kaj->kij", orient.frames, orient.frames)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(orient.frames), 1.0, atol=1e-14)
    assert np.isclose(orient.weights.sum(), 1.0)


def test_localisation_projects_the_strain_on_each_cell_axis():
    orient = orientations_3d(7, 2)
    rng = np.random.default_rng(0)
    d_eps = rng.normal(size=6)
    local = localise(orient, d_eps)
    tensor = to_tensor(d_eps)
    expected = np.einsum("kia,ij,kja->ka", orient.frames, tensor, orient.frames)
    np.testing.assert_allclose(local, expected, atol=1e-14)


def test_averaging_rotates_the_moments_to_the_macro_frame():
    orient = orientations_3d(7, 3)
    rng = np.random.default_rng(1)
    moment = rng.normal(size=(orient.n_cells, 3, 3))
    moment = moment + moment.transpose(0, 2, 1)
    macro = to_tensor(average_moment(orient, moment))
    expected = np.einsum("k,kia,kab,kjb->ij", orient.weights, orient.frames, moment, orient.frames)
    np.testing.assert_allclose(macro, expected, atol=1e-13)


def test_an_axial_cell_averages_to_an_isotropic_tensor():
    """<n n> = I / 3 over the sphere (exact from order 3)."""
    orient = orientations_3d(5, 1)
    moment = np.zeros((orient.n_cells, 3, 3))
    moment[:, 0, 0] = 1.0
    np.testing.assert_allclose(to_tensor(average_moment(orient, moment)), np.eye(3) / 3.0, atol=1e-14)


@pytest.mark.parametrize("order,n_spins", [(7, 2), (11, 4)])
def test_cells_that_respond_along_their_axes_give_an_isotropic_material(order, n_spins):
    """A cell with S = diag(k_n eps_n, k_t eps_t1, k_t eps_t2) gives a macro stiffness of the isotropic
    form lambda tr(eps) I + 2 G eps: fourth moments <n n n n> are exact from order 5 and the two
    lateral axes enter as I - n n - (terms of the spin) whose average is isotropic for >= 2 spins
    over 90 deg."""
    orient = orientations_3d(order, n_spins)
    k_n, k_t = 3.0, 1.0

    def stress(d_eps):
        local = localise(orient, d_eps)
        moment = np.zeros((orient.n_cells, 3, 3))
        moment[:, 0, 0], moment[:, 1, 1], moment[:, 2, 2] = k_n * local[:, 0], k_t * local[:, 1], k_t * local[:, 2]
        return average_moment(orient, moment)

    columns = np.stack([stress(np.eye(6)[m]) for m in range(6)], axis=1)
    lam, two_g = columns[1, 0], columns[0, 0] - columns[1, 0]
    isotropic = np.zeros((6, 6))
    isotropic[:3, :3] = lam
    isotropic[np.arange(6), np.arange(6)] += two_g
    np.testing.assert_allclose(columns, isotropic, atol=1e-12)
    assert COMPONENTS[0] == "11" and two_g > 0


def test_volume_ratio_factor_multiplies_the_three_normal_stretches():
    assert volume_ratio_factor(np.array([0.1, -0.2, 0.3, 9.0, 9.0, 9.0])) == pytest.approx(0.9 * 1.2 * 0.7)


def test_staggered_spins_sample_distinct_phases_and_keep_each_axis_equally_spaced():
    """Staggering (the default) gives every axis its own spin phase, frac(k g) of a spin step; each
    axis keeps n equally spaced spins over the period, so the isotropy of the rule is kept."""
    from homogenization.material.orientation import SPIN_STAGGER

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
