"""MesoNet: the structure of the prediction (homogeneous in the probe, linear relaxation of F)."""

import numpy as np
import pytest
import torch

from training.cell_physics import CellSchema
from training.network import MesoNet, n_features
from warp_hcell.mesostructures.hcell import h_cell


@pytest.fixture(scope="module")
def net():
    meso = h_cell(55.0, 0.5)
    schema = CellSchema.from_arrays(radius=meso.radius, reference_position=meso.position,
                                    reference_cell_size=meso.cell_size, driven=meso.driven, pairs=meso.pairs,
                                    outer=meso.outer, kn=2e8, kt=1e8, mu=0.577, contact_tolerance=1e-9)
    torch.manual_seed(0)
    active = torch.zeros(15, dtype=torch.bool)
    active[:6] = True
    model = MesoNet(schema, active, (16, 16))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0.0, 0.3)
    return model.eval(), meso


def _state(meso, n=5, squeeze=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    size = torch.tensor(np.tile(meso.cell_size * (1 - squeeze), (n, 1)))
    free = torch.tensor(meso.position[~meso.driven][None] * (1 - squeeze) + rng.normal(scale=1e-5, size=(n, 4)))
    return size, free, torch.tensor(rng.normal(scale=1e3, size=(n, 15)))


def test_feature_count_and_float64(net):
    model, meso = net
    feats, m, F = model.raw_features(*_state(meso), torch.full((5, 2), 1e-4))
    assert feats.shape == (5, n_features(4, 6)) and feats.dtype == torch.float64
    assert F.shape == (5, 4) and torch.any(F != 0)


def test_displacement_is_homogeneous_of_degree_one_in_the_probe_plus_relaxation(net):
    model, meso = net
    state = _state(meso)
    d = torch.tensor(np.random.default_rng(1).normal(size=(5, 2)) * 1e-4)
    with torch.no_grad():
        at_zero = model.displacement(*state, torch.zeros(5, 2))
        one, two, three = (model.displacement(*state, k * d) for k in (1, 2, 3))
    # for a fixed direction: d_free = |d_eps| a(state, u) + b(state, u, F)
    torch.testing.assert_close(three - one, 2 * (two - one), rtol=1e-9, atol=1e-18)
    assert torch.all(at_zero.abs().amax(dim=1) > 0)  # unbalanced states relax with a zero probe


def test_a_balanced_state_with_a_zero_probe_does_not_move(net):
    model, meso = net
    size = torch.tensor(meso.cell_size[None])
    free = torch.tensor(meso.position[~meso.driven][None])
    with torch.no_grad():
        # touching grains: overlaps of a few ulps give forces of ~1e-8 N at most
        assert torch.all(model.displacement(size, free, torch.zeros(1, 15), torch.zeros(1, 2)).abs() < 1e-14)


def test_a_cells_prediction_does_not_depend_on_its_batch(net):
    model, meso = net
    state = _state(meso)
    d = torch.full((5, 2), 1e-4)
    with torch.no_grad():
        whole = model.displacement(*state, d)
        alone = model.displacement(*(s[2:3] for s in state), d[2:3])
    torch.testing.assert_close(alone, whole[2:3], rtol=1e-12, atol=1e-18)  # BLAS blocking: last-ulp only


@pytest.mark.parametrize("hidden", [(), (0, 4)])
def test_bad_hidden_widths_are_refused(net, hidden):
    with pytest.raises(ValueError, match="hidden"):
        MesoNet(net[0].schema, net[0].active, hidden)


def test_load_features_are_each_pairs_normal_force_over_the_cells_largest(net):
    model, meso = net
    plain = MesoNet(model.schema, model.active, (8,), load_features=True)
    size, free, shear = _state(meso, squeeze=2e-4)
    size, free, shear = (t[:2].clone() for t in (size, free, shear))
    size[1] *= 1.01  # the second cell is dilated: no pair carries a force
    free[1] *= 1.01
    d = torch.full((2, 2), 1e-4)
    base = model.raw_features(size, free, shear, d)[0]
    feats = plain.raw_features(size, free, shear, d)[0]
    assert feats.shape == (2, n_features(4, 6, True)) == (2, n_features(4, 6) + 6)
    torch.testing.assert_close(feats[:, :base.shape[1]], base, rtol=0, atol=0)
    x = torch.tensor(meso.position).repeat(2, 1, 1)
    x[:, ~torch.tensor(meso.driven)] = free.reshape(2, -1)
    x[:, torch.tensor(meso.driven)] = (torch.tensor(meso.position / meso.cell_size)[None] * size[:, None, :])[
        :, torch.tensor(meso.driven)]
    pairs = torch.tensor(meso.pairs)
    overlap = 2 * torch.tensor(meso.radius)[pairs[:, 0]] - torch.linalg.vector_norm(x[:, pairs[:, 1]] - x[:, pairs[:, 0]], dim=2)
    fn = torch.clamp(overlap, min=0)[0]
    assert int((fn > 0).sum()) >= 2
    torch.testing.assert_close(feats[0, base.shape[1]:], fn[:6] / fn.max(), rtol=1e-9, atol=0)
    torch.testing.assert_close(feats[1, base.shape[1]:], torch.zeros(6, dtype=torch.float64), rtol=0, atol=0)
