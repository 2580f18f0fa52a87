"""``warp_hcell.core.libm``: its functions within 2 ulp of the exact value (mpmath), C99's special
values, and the same bits on every CPU and C library (a committed digest of their results,
checked by ``make determinism`` under every CPU-feature setting, glibc's included)."""

import hashlib
import math

import mpmath
import numpy as np
import pytest

from warp_hcell.core import libm

OUTPUT_DIGEST = "a05caca79ca433717b9417cd695821a1980a89f913ebe1f11bb768d205aef6c1"
"""sha256 of the bytes of exp, log, sin, cos, atan2 and standard_normal on ``_inputs()``."""


def _inputs():
    rng = np.random.default_rng(11)
    x = np.concatenate([rng.uniform(-745.0, 709.7, 2000), rng.uniform(-1.0, 1.0, 2000), rng.uniform(-1e-8, 1e-8, 200)])
    positive = np.concatenate([libm.exp(rng.uniform(-740.0, 709.0, 2000)), rng.uniform(0.5, 2.0, 2000),
                               1.0 + rng.uniform(-1e-6, 1e-6, 200), [5e-324, 1.7976931348623157e308]])
    angle = np.concatenate([rng.uniform(-7.0, 7.0, 2000), rng.uniform(-3000.0, 3000.0, 1000),
                            rng.uniform(-1e-5, 1e-5, 200), np.arange(1, 200) * (np.pi / 2.0), [355.0, 1e6]])
    y, x2 = rng.standard_normal((2, 3000)) * libm.exp(rng.uniform(-20.0, 20.0, (2, 3000)))
    return x, positive, angle, y, x2


def _ulp_errors(got, exact):
    out = []
    for g, e in zip(got, exact):
        ef = float(e)
        if math.isinf(ef) or e == 0:
            out.append(0.0 if ef == g else math.inf)
            continue
        ulp = math.ulp(ef)
        if math.frexp(abs(ef))[0] == 0.5 and abs(e) < abs(ef) and abs(ef) > 2.3e-308:
            ulp /= 2.0  # the exact value lies in the binade below
        out.append(float(abs(mpmath.mpf(float(g)) - e) / ulp))
    return np.array(out)


def test_within_two_ulp_of_the_exact_value():
    mpmath.mp.prec = 120
    x, positive, angle, y, x2 = _inputs()
    cases = {"exp": (libm.exp(x), [mpmath.exp(v) for v in x]),
             "log": (libm.log(positive), [mpmath.log(v) for v in positive]),
             "sin": (libm.sin(angle), [mpmath.sin(v) for v in angle]),
             "cos": (libm.cos(angle), [mpmath.cos(v) for v in angle]),
             "atan2": (libm.atan2(y, x2), [mpmath.atan2(a, b) for a, b in zip(y, x2)])}
    worst = {name: _ulp_errors(got, exact).max() for name, (got, exact) in cases.items()}
    assert max(worst.values()) <= 2.0, worst


def test_special_values_are_c99_s():
    signed = [0.0, -0.0, 1.0, -1.0, 1e-300, -1e-300, 1e300, -1e300, math.inf, -math.inf]
    for a in signed:
        for b in signed:
            got, want = float(libm.atan2(a, b)), math.atan2(a, b)
            assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want), (a, b)
    assert np.isnan(libm.atan2(math.nan, 1.0)) and np.isnan(libm.atan2(1.0, math.nan))
    np.testing.assert_array_equal(libm.exp([-math.inf, math.inf, 0.0, 710.0, -746.0, 709.78]),
                                  [0.0, math.inf, 1.0, math.inf, 0.0, math.exp(709.78)])
    np.testing.assert_array_equal(libm.log([0.0, -0.0, 1.0, math.inf]), [-math.inf, -math.inf, 0.0, math.inf])
    assert np.isnan(libm.log(-1.0)) and np.isnan(libm.exp(math.nan)) and np.isnan(libm.sin(math.inf))
    assert math.copysign(1.0, float(libm.sin(-0.0))) == -1.0 and float(libm.cos(0.0)) == 1.0
    with pytest.raises(ValueError):
        libm.sin(1e7)


def test_shapes_and_normal_draws():
    x = np.linspace(0.1, 3.0, 12).reshape(4, 3)
    for f in (libm.exp, libm.log, libm.sin, libm.cos):
        assert f(x).shape == (4, 3) and f(x).dtype == np.float64 and f(2.0).shape == ()
    assert libm.atan2(x, 1.0).shape == (4, 3)
    z = libm.standard_normal(np.random.default_rng(1), (50001, 2))
    assert z.shape == (50001, 2)
    assert abs(z.mean()) < 0.01 and abs(z.std() - 1.0) < 0.01 and abs(np.mean(z**4) - 3.0) < 0.1


@pytest.mark.determinism
def test_the_same_bits_on_every_cpu_and_c_library():
    x, positive, angle, y, x2 = _inputs()
    h = hashlib.sha256()
    for out in (libm.exp(x), libm.log(positive), libm.sin(angle), libm.cos(angle), libm.atan2(y, x2),
                libm.standard_normal(np.random.default_rng(7), 1001)):
        h.update(np.ascontiguousarray(out, dtype=np.float64).tobytes())
    assert h.hexdigest() == OUTPUT_DIGEST
