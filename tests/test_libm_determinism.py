"""The C-library functions the DEM database uses instead of numpy's (``warp_hcell.core.libm``), and the
assumption its promise leans on: numpy's float64 sin and cos are the C library's on this CPU, under
every numpy dispatch level ``make determinism`` sets (docs/determinism.md)."""

import math

import numpy as np
import pytest

from warp_hcell.core import libm


def _c_library(function, *arrays):
    return np.array([function(*values) for values in zip(*(a.ravel() for a in arrays))]).reshape(arrays[0].shape)


def test_libm_is_math_element_by_element():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-20.0, 20.0, (2, 50, 3))
    positive = np.abs(x) + 1e-12
    assert libm.exp(x).shape == (50, 3) and libm.exp(x).dtype == np.float64
    np.testing.assert_array_equal(libm.exp(x), _c_library(math.exp, x))
    np.testing.assert_array_equal(libm.log(positive), _c_library(math.log, positive))
    np.testing.assert_array_equal(libm.atan2(y, x), _c_library(math.atan2, y, x))
    assert libm.log(2.0).shape == () and float(libm.log(2.0)) == math.log(2.0)


@pytest.mark.determinism
def test_numpy_sin_and_cos_are_the_c_library_s():
    """The database's angles (probe directions, leg directions, turns, the cell's geometry) go
    through numpy's sin and cos; were numpy to vectorise them with other last bits, the database
    would differ between CPUs, and this fails first."""
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.uniform(-2.0 * np.pi, 2.0 * np.pi, 20000), rng.uniform(-1e3, 1e3, 2000)])
    np.testing.assert_array_equal(np.sin(x), _c_library(math.sin, x))
    np.testing.assert_array_equal(np.cos(x), _c_library(math.cos, x))
