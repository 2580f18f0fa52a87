"""Element-wise exp, log and atan2 by the C library (Python's ``math``): the same bits on any x86-64 CPU.

numpy's float64 exp, log and arctan2 (also tan, power, expm1, log1p, cbrt, arcsin, arccos,
arctan) run AVX-512 kernels on CPUs that have AVX-512 and the C library's functions elsewhere,
and the two differ in the last bit of some results (docs/determinism.md: the measurement).
The DEM database promises the same bits on every CPU, so its draws and observables call these
instead: one C-library call per element, the variant that glibc picks on every CPU with AVX2
and FMA. About 0.1 us an element: for draws and per-sample values, not for inner loops.
"""

from __future__ import annotations

import math

import numpy as np

_EXP = np.frompyfunc(math.exp, 1, 1)
_LOG = np.frompyfunc(math.log, 1, 1)
_ATAN2 = np.frompyfunc(math.atan2, 2, 1)


def exp(x: np.ndarray | float) -> np.ndarray:
    """exp(x), e to the power x, element by element, float64, the shape of ``x``."""
    return np.asarray(_EXP(x), dtype=np.float64)


def log(x: np.ndarray | float) -> np.ndarray:
    """Natural logarithm of ``x`` > 0 element by element, float64, the shape of ``x``."""
    return np.asarray(_LOG(x), dtype=np.float64)


def atan2(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The angle [rad] in (-pi, pi] of the point (x, y) element by element, float64, the broadcast shape."""
    return np.asarray(_ATAN2(y, x), dtype=np.float64)
