"""``training.perceptron``: the float32 perceptron against float64 references, and its per-cell determinism."""

import numba
import numpy as np
import pytest

from training.mlp import Perceptron
from training.perceptron import BLOCK, tanh32


@numba.njit
def _tanh32_of(x, out):
    for i in range(x.shape[0]):
        out[i] = tanh32(x[i])


def _tanh32(x: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float32)
    out = np.empty_like(x)
    _tanh32_of(x, out)
    return out


def test_tanh32_is_within_a_few_float32_ulp_of_tanh():
    x = np.concatenate([np.linspace(-12.0, 12.0, 400_001), np.logspace(-30, 1.2, 20_001)]).astype(np.float32)
    exact = np.tanh(x.astype(np.float64))
    ulp = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    error = np.abs(_tanh32(x) - exact) / ulp
    assert error.max() <= 8.0
    assert np.median(error) <= 1.0


def test_tanh32_is_odd_and_saturates():
    x = np.logspace(-20, 2, 5001).astype(np.float32)
    np.testing.assert_array_equal(_tanh32(-x), -_tanh32(x))
    assert _tanh32(np.array([0.0], np.float32))[0] == 0.0
    big = _tanh32(np.array([9.0, 20.0, 1e30], np.float32))
    assert np.all(np.abs(big - 1.0) <= np.spacing(np.float32(1.0)))


def _net(rng, widths=(66, 40, 40, 20)):
    return [(rng.standard_normal((b, a)) / np.sqrt(a), rng.standard_normal(b) * 0.3) for a, b in zip(widths[:-1], widths[1:])]


def _reference(weights, h):
    """float64 forward pass and, for inputs 0 and 1, its derivative (n_outputs, 2, n)."""
    a, da = h.astype(np.float64), np.zeros((2, h.shape[0], h.shape[1]))
    da[0, 0], da[1, 1] = 1.0, 1.0
    for index, (w, b) in enumerate(weights):
        a, da = w @ a + b[:, None], np.einsum("jk,dkc->djc", w, da)
        if index < len(weights) - 1:
            a = np.tanh(a)
            da = da * (1.0 - a * a)
    return a, da


def test_forward_and_jvp_match_a_float64_reference():
    rng = np.random.default_rng(0)
    weights = _net(rng)
    h = rng.standard_normal((66, 300)).astype(np.float32)
    net = Perceptron(weights)
    layers = net.buffers(300)
    out = net.forward(h, layers)
    expected, expected_dot = _reference(weights, h)
    assert np.abs(out - expected).max() <= 2e-6 * np.abs(expected).max()
    for j in range(2):
        unit = np.zeros((2, 300), np.float32)
        unit[j] = 1.0
        jvp = net.jvp(0, unit, layers)
        assert np.abs(jvp - expected_dot[j]).max() <= 2e-6 * np.abs(expected_dot[j]).max()


@pytest.mark.parametrize("n", [1, 3, BLOCK - 1, BLOCK, BLOCK + 1, 2 * BLOCK + 77])
def test_a_cells_output_is_the_same_in_any_batch_at_any_place(n):
    """Odd widths exercise the layer's tails (odd input and output counts)."""
    rng = np.random.default_rng(1)
    weights = _net(rng, (67, 41, 39, 21))
    net = Perceptron(weights)
    h = rng.standard_normal((67, 400)).astype(np.float32)
    whole = net.forward(h, net.buffers(400)).copy()
    index = rng.integers(0, 400, size=n)
    part = net.forward(np.ascontiguousarray(h[:, index]), net.buffers(n))
    np.testing.assert_array_equal(part, whole[:, index])
