"""``training.fast_cells``: numba's set-up for the compiled kernels leaves ``scipy.linalg`` unimported."""

import subprocess
import sys

_CODE = """
import sys
import numba
import numpy as np
from training.fast_cells import grain_positions
x = np.empty((6, 2, 3))
grain_positions(np.ones((2, 3)), np.ones((4, 3)), np.ones((6, 2)), np.array([[1, 0], [1, 1], [2, 0], [2, 1]]), x)
print("scipy.linalg" in sys.modules, "scipy.linalg.cython_blas" in sys.modules)
dot = numba.njit(lambda a, b: np.dot(a, b))
a = np.arange(4.0).reshape(2, 2)
print(bool((dot(a, a) == a @ a).all()))
import scipy.linalg
print(scipy.linalg.cython_blas.__name__)
"""


def test_a_compiled_call_imports_no_scipy_linalg_and_blas_still_works():
    """The first compiled call sets numba up without ``scipy.linalg`` (its BLAS check loads ``cython_blas``
    alone); numba's ``np.dot`` and a later ``import scipy.linalg`` still work as usual."""
    done = subprocess.run([sys.executable, "-c", _CODE], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False", "True", "scipy.linalg.cython_blas"]
