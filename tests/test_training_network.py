"""CellNet: shapes, float64, buffers in the state_dict, homogeneity in the probe, batch invariance."""

import math

import numpy as np
import pytest
import torch

from training.network import DEFAULT_HIDDEN, CellNet, dimensionless_state, features, probe_split

KN, D, MU = 2e8, 1.0, 0.5


def _net(seed: int = 0, hidden=DEFAULT_HIDDEN) -> CellNet:
    torch.manual_seed(seed)
    net = CellNet(hidden, kn=KN, diameter=D, mu=MU)
    net.set_normalisation(np.zeros(12), np.full(12, 0.5), np.full(4, 0.1), np.full(4, 2.0))
    return net.eval()


def _inputs(n: int, seed: int = 1) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    d_eps = rng.normal(scale=1e-5, size=(n, 2))
    state = np.column_stack([rng.uniform(35, 80, n), rng.uniform(0, 5e6, (n, 2)), rng.uniform(-1e6, 1e6, n),
                             rng.uniform(1.5, 2.0, n), rng.uniform(1.0, 1.7, n)])
    return torch.from_numpy(np.column_stack([d_eps, state]))


def test_predict_maps_n_by_8_to_n_by_4_in_float64():
    out = _net().predict(_inputs(5))
    assert out.shape == (5, 4) and out.dtype == torch.float64


def test_zero_probe_leaves_the_state_exactly_unchanged():
    x = _inputs(6)
    x[:, :2] = 0.0
    assert torch.equal(_net().predict(x), x[:, 2:6])


def test_increment_is_homogeneous_of_degree_one_in_the_probe():
    net, x = _net(), _inputs(7)
    scaled = x.clone()
    scaled[:, :2] *= 10.0
    assert torch.allclose(net.increment(scaled), 10.0 * net.increment(x), rtol=1e-12, atol=0.0)
    opposite = x.clone()
    opposite[:, :2] *= -1.0  # another direction: not simply the negative (incremental nonlinearity)
    assert not torch.allclose(net.increment(opposite), -net.increment(x), rtol=1e-3)


def test_derived_features_flag_contacts_friction_ratio_and_sliding():
    x = torch.tensor([[3e-5, 4e-5, 60.0, 0.02 * KN, 0.0, -0.01 * KN, 1.9, 1.7],
                      [0.0, 0.0, 60.0, 0.0, 0.01 * KN, 0.0, 1.9, 1.7],
                      [1e-5, 0.0, 60.0, 0.02 * KN, 0.01 * KN, 0.4 * 0.02 * KN, 1.9, 1.7]], dtype=torch.float64)
    raw, magnitude = features(x, KN, D, 0.5)
    assert raw.shape == (3, 12) and torch.allclose(magnitude[:, 0], torch.tensor([5e-5, 0.0, 1e-5], dtype=torch.float64))
    expected = [[1.0, 0.0, -0.5, -1.0], [0.0, 1.0, 0.0, 0.0], [1.0, 1.0, 0.4, 0.0]]
    assert torch.allclose(raw[:, 8:], torch.tensor(expected, dtype=torch.float64))


def test_normalisation_buffers_travel_in_the_state_dict():
    net = _net()
    state = net.state_dict()
    for name in ("kn", "diameter", "mu", "feature_mean", "feature_std", "rate_mean", "rate_std"):
        assert name in state
    assert float(state["kn"]) == KN and torch.all(state["feature_std"] == 0.5)
    fresh = CellNet(DEFAULT_HIDDEN)
    fresh.load_state_dict(state)
    x = _inputs(4)
    assert torch.equal(fresh.eval().predict(x), net.predict(x))


def test_a_cells_prediction_does_not_depend_on_its_batch():
    net, x = _net(), _inputs(64)
    batch = net.predict(x)
    alone = torch.cat([net.predict(x[i:i + 1]) for i in (0, 17, 63)])
    assert torch.allclose(alone, batch[[0, 17, 63]], rtol=1e-13, atol=0.0)


def test_dimensionless_units_and_probe_split():
    state = torch.tensor([[90.0, KN * D * 0.01, 0.0, -KN * D * 0.02, 2.0 * D, 0.5 * D]], dtype=torch.float64)
    assert torch.allclose(dimensionless_state(state, KN, D),
                          torch.tensor([[math.pi / 2, 0.01, 0.0, -0.02, 2.0, 0.5]], dtype=torch.float64))
    magnitude, direction = probe_split(torch.tensor([[3e-5, -4e-5], [0.0, 0.0]], dtype=torch.float64))
    assert torch.allclose(magnitude[:, 0], torch.tensor([5e-5, 0.0], dtype=torch.float64))
    assert torch.allclose(direction, torch.tensor([[0.6, -0.8], [0.0, 0.0]], dtype=torch.float64))


@pytest.mark.parametrize("hidden", [(), (8, 0)])
def test_bad_hidden_widths_are_refused(hidden):
    with pytest.raises(ValueError, match="hidden"):
        CellNet(hidden)


def test_hidden_layers_are_configurable():
    net = _net(hidden=(16, 4))
    linear = [m for m in net.mlp if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linear] == [(12, 16), (16, 4), (4, 4)]
    assert sum(isinstance(m, torch.nn.Tanh) for m in net.mlp) == 2
