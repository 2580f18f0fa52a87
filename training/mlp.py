"""The meso-ANN's perceptron for inference: its float32 weights and the scratch of its layers, cells last.

``Perceptron`` holds a tanh multilayer perceptron of ``training.network.MesoNet`` and evaluates it (and its
forward-mode derivative) with the compiled kernels of ``training.perceptron``, whose arithmetic does not depend
on the batch or the CPU's vector width; those kernels (numba) are imported on the first evaluation, so that a
process whose step is precompiled (``training.precompiled``) imports no numba.
"""

from __future__ import annotations

import numpy as np

LANES = 16
"""``Perceptron.padded_buffers`` rounds the cells up to a multiple of this, so that the layers after the first
run whole vectors, without a scalar remainder (a speed setting; results do not depend on it)."""


def padded_cells(n: int) -> int:
    """Columns of ``Perceptron.padded_buffers`` for n cells: n rounded up to a multiple of ``LANES``, or n below
    ``LANES`` (where the loops' scalar remainder costs less than one whole vector)."""
    return n if n < LANES else -(-n // LANES) * LANES


class Perceptron:
    """A tanh multilayer perceptron (hidden layers tanh, output layer linear) in float32, cells last.

    Args:
        weights: per layer the weight (n_out, n_in) and bias (n_out,), input layer first
            (converted to float32 C arrays).
    """

    def __init__(self, weights: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.weight = tuple(np.ascontiguousarray(w, dtype=np.float32) for w, _ in weights)
        self.bias = tuple(np.ascontiguousarray(b, dtype=np.float32) for _, b in weights)
        self._zero_bias = [np.zeros_like(b) for b in self.bias]
        self.widths = tuple(w.shape[0] for w in self.weight)
        """Output width of every layer."""
        self._first_columns: dict[tuple[int, int], np.ndarray] = {}

    @property
    def n_inputs(self) -> int:
        """Number of inputs of the first layer."""
        return int(self.weight[0].shape[1])

    def buffers(self, n: int) -> tuple[np.ndarray, ...]:
        """Scratch outputs of every layer for ``n`` cells, (width, n) float32 each."""
        return tuple(np.empty((width, n), dtype=np.float32) for width in self.widths)

    def padded_buffers(self, n: int) -> tuple[np.ndarray, ...]:
        """``buffers`` of ``padded_cells(n)`` cells, zeros: ``forward`` of n cells writes cell c in column c of
        every layer and runs the layers after the first on every column (the other columns are scratch, their
        values finite)."""
        return tuple(np.zeros((width, padded_cells(n)), dtype=np.float32) for width in self.widths)

    def forward(self, h: np.ndarray, layers: tuple[np.ndarray, ...]) -> np.ndarray:
        """Network output (n_outputs, n) of inputs ``h`` (n_inputs, n) float32 C-contiguous; ``layers`` from
        ``buffers(n)`` receive every layer's output (the hidden activations stay there for ``jvp``)."""
        from training.perceptron import forward_layers  # noqa: PLC0415 (numba: imported on first use)

        forward_layers(self.weight, self.bias, h, layers)
        return layers[-1]

    def jvp(self, first: int, h_dot: np.ndarray, layers: tuple[np.ndarray, ...]) -> np.ndarray:
        """Derivative of the output (n_outputs, n) along one direction, given that of the inputs
        ``first``, ``first + 1``, ... (``h_dot`` (n_varying, n); every other input constant) and the
        activations ``forward`` left in ``layers``."""
        from training.perceptron import dense, scale_by_tanh_derivative  # noqa: PLC0415 (numba: imported on first use)

        last = len(self.weight) - 1
        for index, (weight, zero, h) in enumerate(zip(self.weight, self._zero_bias, layers)):
            if index == 0:
                key = (first, h_dot.shape[0])
                if key not in self._first_columns:
                    self._first_columns[key] = np.ascontiguousarray(weight[:, first:first + h_dot.shape[0]])
                weight = self._first_columns[key]
            out_dot = np.empty((weight.shape[0], h_dot.shape[1]), dtype=np.float32)
            dense(weight, zero, h_dot, out_dot, False)
            if index < last:
                scale_by_tanh_derivative(h, out_dot)
            h_dot = out_dot
        return h_dot
