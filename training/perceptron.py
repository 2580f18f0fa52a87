"""The meso-ANN's perceptron for inference: float32, one fixed sequence of operations per cell.

The kernels here evaluate the tanh multilayer perceptron of ``training.network.MesoNet`` (and
its forward-mode derivative) on a batch of cells laid out cells last, (n_features, n_cells),
without BLAS. Every output of every cell is computed by the same IEEE-754 operations in the
same order whatever the batch, the cell's place in it and the CPU's vector width:

- a layer output starts from the bias and accumulates ``weight[j, k] * h[k]`` for
  k = 0, 1, ..., n_in - 1 in that order, each term by one fused multiply-add (``_fma32``, the
  LLVM intrinsic: one rounding, in hardware where the CPU has FMA, in software otherwise);
- the hidden activation is ``tanh32``, a rational function evaluated with additions,
  multiplications, FMAs and one division only (no library call whose result could depend on
  the CPU or on vectorisation);
- loops over cells are innermost and each cell is one lane: vectorising them (4, 8 or 16
  lanes, or none) changes the speed, not a bit of the result. Nothing reduces across cells.

BLAS kernels do not give this: their blocking and their choice of kernel depend on the CPU and on
where a column sits in the matrix, so a cell's output moved in its last bits with its place in
the batch.

Arrays are float32, C-contiguous, cells along the last axis; the number of cells need not be
a multiple of anything (``BLOCK`` only sets the cache tile).
"""

from __future__ import annotations

import numba
import numpy as np
from numba.extending import intrinsic

BLOCK = 512
"""Cells per cache tile of a layer (a speed setting; results do not depend on it)."""

TANH_CLIP = 9.0
"""``|x|`` beyond which tanh32 returns its value at +-9 (within 2e-8 of +-1, below float32's resolution)."""

# tanh(x) ~ x P(u) / Q(u), u = (x / 9)^2, |x| <= 9: a least-squares rational fit of relative error with
# Lawson reweighting on 4e4 Chebyshev-spaced points of [0, 9]; max relative error 3.8e-9 in exact
# arithmetic (evaluated in float32: a few units in the last place, tested against float64 tanh).
_TANH_P = (0.9999999962374895, 11.191764063321012, 26.53681927216796, 16.968360162944737, 1.833949076767449,
           -0.09735439987746108, 0.005943551109727441)
_TANH_Q = (1.0, 38.191762401312445, 182.91455898929954, 226.44291470952976, 68.40611514657363)
_P = tuple(np.float32(c) for c in _TANH_P)
_Q = tuple(np.float32(c) for c in _TANH_Q)
_CLIP = np.float32(TANH_CLIP)
_INV_CLIP_SQ = np.float32(1.0 / TANH_CLIP**2)
_ONE = np.float32(1.0)


@intrinsic
def _fma32(typingctx, a, b, c):
    """a * b + c with one rounding (``llvm.fma``) for float32 scalars."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return numba.float32(numba.float32, numba.float32, numba.float32), codegen


@numba.njit(inline="always", error_model="numpy")
def tanh32(x):
    """float32 tanh of a float32 ``x``: clip to [-9, 9], then x P(u) / Q(u) by Horner with FMAs (module docstring)."""
    y = min(max(x, -_CLIP), _CLIP)
    u = y * y * _INV_CLIP_SQ
    p = _fma32(_fma32(_fma32(_fma32(_fma32(_fma32(_P[6], u, _P[5]), u, _P[4]), u, _P[3]), u, _P[2]), u, _P[1]),
               u, _P[0])
    q = _fma32(_fma32(_fma32(_fma32(_Q[4], u, _Q[3]), u, _Q[2]), u, _Q[1]), u, _Q[0])
    return y * p / q


@numba.njit(inline="always", error_model="numpy")
def _dot8(w, x, acc):
    """acc + w[0] x[0] + w[1] x[1] + ... + w[7] x[7], the terms added in that order, each by one FMA
    (``w``, ``x``: tuples of 8 float32; ``acc`` float32)."""
    return _fma32(w[7], x[7], _fma32(w[6], x[6], _fma32(w[5], x[5], _fma32(w[4], x[4], _fma32(
        w[3], x[3], _fma32(w[2], x[2], _fma32(w[1], x[1], _fma32(w[0], x[0], acc))))))))


@numba.njit(inline="always", error_model="numpy")
def _eight(weight, j, k):
    """weight[j, k], ..., weight[j, k + 7] as a tuple (kept in registers by the pass over the cells)."""
    return (weight[j, k], weight[j, k + 1], weight[j, k + 2], weight[j, k + 3], weight[j, k + 4], weight[j, k + 5],
            weight[j, k + 6], weight[j, k + 7])


@numba.njit(cache=True, error_model="numpy")
def _accumulate8(weight, h, out, k, lo, hi, squash):
    """out[j, c] += weight[j, k] h[k, c] + ... + weight[j, k + 7] h[k + 7, c] for every output j and
    the cells lo <= c < hi, the eight terms in input order by FMAs (``_dot8``); three outputs share
    each pass over the cells, so that each input is loaded once per three outputs and each output
    once per eight inputs. ``squash``: then ``tanh32`` of the sum (the layer's last inputs, in the same
    pass). Shapes as in ``dense``."""
    m = hi - lo
    h0, h1, h2, h3 = h[k, lo:hi], h[k + 1, lo:hi], h[k + 2, lo:hi], h[k + 3, lo:hi]
    h4, h5, h6, h7 = h[k + 4, lo:hi], h[k + 5, lo:hi], h[k + 6, lo:hi], h[k + 7, lo:hi]
    n_out = weight.shape[0]
    j = 0
    while j + 3 <= n_out:
        r0, r1, r2 = out[j, lo:hi], out[j + 1, lo:hi], out[j + 2, lo:hi]
        w0, w1, w2 = _eight(weight, j, k), _eight(weight, j + 1, k), _eight(weight, j + 2, k)
        for c in range(m):
            x = (h0[c], h1[c], h2[c], h3[c], h4[c], h5[c], h6[c], h7[c])
            s0, s1, s2 = _dot8(w0, x, r0[c]), _dot8(w1, x, r1[c]), _dot8(w2, x, r2[c])
            r0[c] = tanh32(s0) if squash else s0
            r1[c] = tanh32(s1) if squash else s1
            r2[c] = tanh32(s2) if squash else s2
        j += 3
    if j + 2 == n_out:
        r0, r1, w0, w1 = out[j, lo:hi], out[j + 1, lo:hi], _eight(weight, j, k), _eight(weight, j + 1, k)
        for c in range(m):
            x = (h0[c], h1[c], h2[c], h3[c], h4[c], h5[c], h6[c], h7[c])
            s0, s1 = _dot8(w0, x, r0[c]), _dot8(w1, x, r1[c])
            r0[c] = tanh32(s0) if squash else s0
            r1[c] = tanh32(s1) if squash else s1
        j += 2
    while j < n_out:
        r0, w0 = out[j, lo:hi], _eight(weight, j, k)
        for c in range(m):
            s0 = _dot8(w0, (h0[c], h1[c], h2[c], h3[c], h4[c], h5[c], h6[c], h7[c]), r0[c])
            r0[c] = tanh32(s0) if squash else s0
        j += 1


@numba.njit(cache=True, error_model="numpy")
def _accumulate2(weight, h, out, k, lo, hi, squash):
    """out[j, c] += weight[j, k] h[k, c] + weight[j, k + 1] h[k + 1, c] (two FMAs, in that order) for every
    output j and the cells lo <= c < hi, three outputs per pass, then ``tanh32`` where ``squash``
    (``_accumulate8`` for the inputs left)."""
    m = hi - lo
    h0, h1 = h[k, lo:hi], h[k + 1, lo:hi]
    n_out = weight.shape[0]
    j = 0
    while j + 3 <= n_out:
        r0, r1, r2 = out[j, lo:hi], out[j + 1, lo:hi], out[j + 2, lo:hi]
        a0, b0, a1, b1 = weight[j, k], weight[j, k + 1], weight[j + 1, k], weight[j + 1, k + 1]
        a2, b2 = weight[j + 2, k], weight[j + 2, k + 1]
        for c in range(m):
            s0 = _fma32(b0, h1[c], _fma32(a0, h0[c], r0[c]))
            s1 = _fma32(b1, h1[c], _fma32(a1, h0[c], r1[c]))
            s2 = _fma32(b2, h1[c], _fma32(a2, h0[c], r2[c]))
            r0[c] = tanh32(s0) if squash else s0
            r1[c] = tanh32(s1) if squash else s1
            r2[c] = tanh32(s2) if squash else s2
        j += 3
    while j < n_out:
        r0, a0, b0 = out[j, lo:hi], weight[j, k], weight[j, k + 1]
        for c in range(m):
            s0 = _fma32(b0, h1[c], _fma32(a0, h0[c], r0[c]))
            r0[c] = tanh32(s0) if squash else s0
        j += 1


@numba.njit(cache=True, error_model="numpy")
def dense(weight, bias, h, out, squash):
    """One layer: out[j, c] = act(bias[j] + sum_k weight[j, k] h[k, c]), the sum in input order by FMAs.

    Args:
        weight: (n_out, n_in) float32; bias: (n_out,) float32 (zeros for a derivative).
        h: inputs (n_in, n) float32, cells last.
        out: (n_out, n) float32, written (must not overlap ``h``).
        squash: apply ``tanh32`` (hidden layer) or not (output layer, derivatives).

    Cells are processed in tiles of ``BLOCK``; inside a tile the inputs are taken eight at a
    time (``_accumulate8``), the last n_in mod 8 two (``_accumulate2``) then one at a time; the
    order of the terms of each sum is k = 0, 1, ... regardless. The tanh is taken in the pass of
    the last inputs, or in a pass of its own after a last input taken alone (the same bits).
    """
    n_out, n_in = weight.shape
    n = h.shape[1]
    for lo in range(0, n, BLOCK):
        hi = min(lo + BLOCK, n)
        for j in range(n_out):
            out[j, lo:hi] = bias[j]
        k = 0
        while k + 8 <= n_in:
            _accumulate8(weight, h, out, k, lo, hi, squash and k + 8 == n_in)
            k += 8
        while k + 2 <= n_in:
            _accumulate2(weight, h, out, k, lo, hi, squash and k + 2 == n_in)
            k += 2
        while k < n_in:
            h0 = h[k, lo:hi]
            for j in range(n_out):
                r0, a0 = out[j, lo:hi], weight[j, k]
                for c in range(hi - lo):
                    r0[c] = _fma32(a0, h0[c], r0[c])
            k += 1
        if squash and n_in % 2 == 1:  # the last input was taken alone
            for j in range(n_out):
                row = out[j, lo:hi]
                for c in range(hi - lo):
                    row[c] = tanh32(row[c])


@numba.njit(cache=True, error_model="numpy")
def forward_layers(weights, biases, h, layers):
    """Every layer in turn (``dense``): tanh hidden layers, linear output layer.

    Args:
        weights, biases: tuples of the layers' (n_out, n_in) and (n_out,) float32 arrays, input layer first.
        h: inputs (n_inputs, n) float32, cells last.
        layers: tuple of (n_out, n) float32 arrays, written: every layer's output, the network's last.
    """
    last = len(weights) - 1
    dense(weights[0], biases[0], h, layers[0], last > 0)
    for index in range(1, len(weights)):
        dense(weights[index], biases[index], layers[index - 1], layers[index], index < last)


@numba.njit(cache=True, error_model="numpy")
def scale_by_tanh_derivative(h, out_dot):
    """``out_dot *= 1 - h^2`` in place (tanh' = 1 - tanh^2 at the layer's output ``h``), (n_rows, n) float32; ``h``
    may have more columns (``training.mlp.Perceptron.padded_buffers``)."""
    for j in range(h.shape[0]):
        h_j, d_j = h[j], out_dot[j]
        for c in range(d_j.shape[0]):
            d_j[c] = d_j[c] * (_ONE - h_j[c] * h_j[c])
