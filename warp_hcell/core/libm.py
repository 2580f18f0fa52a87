"""Element-wise exp, log, sin, cos, atan2 and standard normal draws that are the same bits everywhere.

The C library's exp, log, atan2, sin and cos (and numpy's, which call it or run their own
AVX-512 kernels) pick their code by CPU and platform and differ in last bits. These use only
numpy's ``+``, ``-``, ``*``, ``/``, sqrt, rint, frexp, ldexp, comparisons and ``where``, one ufunc call per
operation (no fused multiply-add can form across calls), in a fixed order: IEEE-754 rounds each
correctly, so the results are the same bits on every CPU, C library and platform. They follow
fdlibm's algorithms (Cody-Waite reduction, fixed polynomials). Max error against mpmath over
~2.6e5 inputs each (``tests/test_libm_determinism.py`` checks <= 2 ulp): exp 0.86 ulp, log
0.79, sin 0.76, cos 0.76, atan2 1.30. The DEM database's draws, angles and observables use
these. About 0.1 us an element in arrays of thousands.
"""

from __future__ import annotations

import numpy as np

_LN2_HI = 6.93147180369123816490e-01  # 0x3FE62E42FEE00000: 32 bits, k * _LN2_HI exact for |k| < 2**21
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_EXP_P = (1.66666666666666019037e-01, -2.77777777770155933842e-03, 6.61375632143793436117e-05,
          -1.65339022054652515390e-06, 4.13813679705723846039e-08)
_EXP_MAX = 7.09782712893383973096e02
_EXP_MIN = -7.45133219101941108420e02
_LG = (6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01, 2.222219843214978396e-01,
       1.818357216161805012e-01, 1.531383769920937332e-01, 1.479819860511658591e-01)
_SQRT_HALF = 0.70710678118654757274
_INV_PIO2 = 6.36619772367581382433e-01
_PIO2 = ((1.57079632673412561417e00, 6.07710050650619224932e-11),  # pio2_1, pio2_1t (33 bits each part)
         (6.07710050630396597660e-11, 2.02226624879595063154e-21),  # pio2_2, pio2_2t
         (2.02226624871116645580e-21, 8.47842766036889956997e-32))  # pio2_3, pio2_3t
_REDUCE_MAX = 2.0**19 * np.pi
"""Largest ``abs(x)`` [rad] sin and cos take (Cody-Waite reduction by pi/2 in three parts)."""
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
      2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
      -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)
_ATAN_HI = (4.63647609000806093515e-01, 7.85398163397448278999e-01, 9.82793723247329054082e-01,
            1.57079632679489655800e00)
_ATAN_LO = (2.26987774529616870924e-17, 3.06161699786838301793e-17, 1.39033110312309984516e-17,
            6.12323399573676603587e-17)
_AT = (3.33333333333329318027e-01, -1.99999999998764832476e-01, 1.42857142725034663711e-01,
       -1.11111104054623557880e-01, 9.09088713343650656196e-02, -7.69187620504482999495e-02,
       6.66107313738753120669e-02, -5.83357013379057348645e-02, 4.97687799461593236017e-02,
       -3.65315727442169155270e-02, 1.62858201153657823623e-02)
_PI = 3.1415926535897931160e00
_PI_LO = 1.2246467991473531772e-16


def _f64(x: np.ndarray | float) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def exp(x: np.ndarray | float) -> np.ndarray:
    """e to the power ``x``, element by element.

    Args:
        x: float64 array (or scalar), any shape.

    Returns:
        float64 array of the shape of ``x`` (0-d for a scalar); inf above 709.78, 0 below -745.13,
        nan for nan.
    """
    x = _f64(x)
    with np.errstate(all="ignore"):
        xs = np.where(np.isfinite(x), np.clip(x, -746.0, 710.0), 0.0)
        k = np.rint(xs * _INV_LN2)
        hi = xs - k * _LN2_HI
        lo = k * _LN2_LO
        r = hi - lo
        t = r * r
        p = _EXP_P[4]
        for coefficient in _EXP_P[3::-1]:
            p = coefficient + t * p
        c = r - t * p
        y = 1.0 - ((lo - (r * c) / (2.0 - c)) - hi)
        ki = k.astype(np.int64)
        # two halves, so that 2**k is never out of range while y * 2**k is not
        out = np.ldexp(np.ldexp(y, ki // 2), ki - ki // 2)
        out = np.where(x > _EXP_MAX, np.inf, np.where(x < _EXP_MIN, 0.0, out))
        return np.where(np.isnan(x), x, out)


def log(x: np.ndarray | float) -> np.ndarray:
    """Natural logarithm of ``x``, element by element.

    Args:
        x: float64 array (or scalar), any shape; > 0 (subnormals included).

    Returns:
        float64 array of the shape of ``x``; -inf for 0, nan for x < 0 or nan, inf for inf.
    """
    x = _f64(x)
    with np.errstate(all="ignore"):
        good = np.isfinite(x) & (x > 0.0)
        m, e = np.frexp(np.where(good, x, 1.0))  # x = m 2**e, m in [0.5, 1)
        low = m < _SQRT_HALF
        m = np.where(low, m * 2.0, m)
        k = (e - low).astype(np.float64)
        f = m - 1.0  # exact (Sterbenz), in [-0.293, 0.414]
        s = f / (2.0 + f)
        z = s * s
        w = z * z
        t1 = w * (_LG[1] + w * (_LG[3] + w * _LG[5]))
        t2 = z * (_LG[0] + w * (_LG[2] + w * (_LG[4] + w * _LG[6])))
        r = t2 + t1
        hfsq = 0.5 * f * f
        out = k * _LN2_HI - ((hfsq - (s * (hfsq + r) + k * _LN2_LO)) - f)
        out = np.where(good, out, np.where(x == 0.0, -np.inf, np.where(x == np.inf, np.inf, np.nan)))
        return out


def _reduce(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x = n pi/2 + (y0 + y1), |y0 + y1| <= ~pi/4: (n mod 4 as int64, y0, y1) (fdlibm's medium case:
    a second and third part of pi/2 where the first leaves more than 16 and 49 bits cancelled)."""
    n = np.rint(x * _INV_PIO2)
    r = x - n * _PIO2[0][0]  # exact: n * pio2_1 has <= 53 bits
    w = n * _PIO2[0][1]
    y0 = r - w
    exponent = np.frexp(x)[1]
    for (part, tail), cancelled in zip(_PIO2[1:], (16, 49)):
        need = exponent - np.frexp(y0)[1] > cancelled
        t = r
        w_next = n * part
        r_next = t - w_next
        w_next = n * tail - ((t - r_next) - w_next)
        r = np.where(need, r_next, r)
        w = np.where(need, w_next, w)
        y0 = r - w
    y1 = (r - y0) - w
    return n.astype(np.int64) & 3, y0, y1


def _kernel_sin(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    z = x * x
    w = z * z
    r = _S[1] + z * (_S[2] + z * _S[3]) + z * w * (_S[4] + z * _S[5])
    v = z * x
    return x - ((z * (0.5 * y - v * r) - y) - v * _S[0])


def _kernel_cos(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    z = x * x
    w = z * z
    r = z * (_C[0] + z * (_C[1] + z * _C[2])) + w * w * (_C[3] + z * (_C[4] + z * _C[5]))
    hz = 0.5 * z
    w = 1.0 - hz
    return w + (((1.0 - w) - hz) + (z * r - x * y))


def _sincos(x: np.ndarray | float, want_sin: bool) -> np.ndarray:
    x = _f64(x)
    finite = np.isfinite(x)
    if np.any(np.abs(x[finite]) > _REDUCE_MAX):
        raise ValueError(f"libm sin and cos take |x| <= {_REDUCE_MAX:.6g} rad")
    with np.errstate(all="ignore"):
        n, y0, y1 = _reduce(np.where(finite, x, 0.0))
        s, c = _kernel_sin(y0, y1), _kernel_cos(y0, y1)
        if want_sin:  # sin(n pi/2 + y) for n mod 4 = 0, 1, 2, 3: s, c, -s, -c
            out = np.where(n == 0, s, np.where(n == 1, c, np.where(n == 2, -s, -c)))
        else:  # cos: c, -s, -c, s
            out = np.where(n == 0, c, np.where(n == 1, -s, np.where(n == 2, -c, s)))
        out = np.where(x == 0.0, x if want_sin else 1.0, out)  # sin(-0) = -0
        return np.where(finite, out, np.nan)


def sin(x: np.ndarray | float) -> np.ndarray:
    """Sine of ``x`` [rad], element by element.

    Args:
        x: float64 array (or scalar), any shape, ``abs(x) <= 2**19 * pi`` (ValueError beyond).

    Returns:
        float64 array of the shape of ``x``; nan for inf or nan.
    """
    return _sincos(x, True)


def cos(x: np.ndarray | float) -> np.ndarray:
    """Cosine of ``x`` [rad], element by element; as ``sin``."""
    return _sincos(x, False)


def _atan_reduced(x: np.ndarray) -> np.ndarray:
    """atan of x >= 0 (fdlibm's five intervals and polynomial); inf gives pi/2."""
    big = x >= 2.4375
    mid2 = (x >= 1.1875) & ~big
    mid1 = (x >= 0.6875) & ~mid2 & ~big
    mid0 = (x >= 0.4375) & ~mid1 & ~mid2 & ~big
    xr = np.where(big, -1.0 / x,
                  np.where(mid2, (x - 1.5) / (1.0 + 1.5 * x),
                           np.where(mid1, (x - 1.0) / (x + 1.0),
                                    np.where(mid0, (2.0 * x - 1.0) / (2.0 + x), x))))
    index = np.where(big, 3, np.where(mid2, 2, np.where(mid1, 1, 0)))
    hi = np.take(_ATAN_HI, index)
    lo = np.take(_ATAN_LO, index)
    z = xr * xr
    w = z * z
    s1 = z * (_AT[0] + w * (_AT[2] + w * (_AT[4] + w * (_AT[6] + w * (_AT[8] + w * _AT[10])))))
    s2 = w * (_AT[1] + w * (_AT[3] + w * (_AT[5] + w * (_AT[7] + w * _AT[9]))))
    reduced = hi - ((xr * (s1 + s2) - lo) - xr)
    small = xr - xr * (s1 + s2)
    return np.where(big | mid2 | mid1 | mid0, reduced, small)


def atan2(y: np.ndarray | float, x: np.ndarray | float) -> np.ndarray:
    """The angle [rad] in [-pi, pi] of the point (x, y), element by element (C99's signs and limits).

    Args:
        y, x: float64 arrays (or scalars) of broadcastable shapes.

    Returns:
        float64 array of the broadcast shape; nan where either is nan.
    """
    y, x = np.broadcast_arrays(_f64(y), _f64(x))
    with np.errstate(all="ignore"):
        ay, ax = np.abs(y), np.abs(x)
        both_inf = np.isinf(ay) & np.isinf(ax)
        q = np.where(both_inf, 1.0, ay / np.where(ax == 0.0, 1.0, ax))
        # |y / x| below 2**-60 with x < 0: the correction below is all there is
        tiny = ax > ay * 2.0**60
        a = np.where(tiny, q, _atan_reduced(q))
        a = np.where(ay == 0.0, 0.0, a)
        a = np.where(both_inf, _PI / 4.0, a)
        negative_x = np.signbit(x)
        # pi - atan(|y/x|), with pi's low part: pi_lo first, then pi
        a = np.where(negative_x, _PI - (a - _PI_LO), a)
        a = np.where(negative_x & both_inf, 3.0 * _PI / 4.0, a)
        steep = ((ay > ax * 2.0**60) | np.isinf(ay)) & ~both_inf  # |y / x| above 2**60, x = 0 included
        a = np.where(steep, _PI / 2.0, a)
        a = np.where(negative_x & (ay == 0.0), _PI, a)
        a = np.where(~negative_x & (ay == 0.0), 0.0, a)
        out = np.where(np.signbit(y), -a, a)
        return np.where(np.isnan(x) | np.isnan(y), np.nan, out)


def standard_normal(gen: np.random.Generator, shape: int | tuple[int, ...]) -> np.ndarray:
    """Standard normal draws of shape ``shape`` from ``gen`` by Box-Muller on ``gen.random``.

    Each pair (z0, z1) = sqrt(-2 log(1 - u0)) (cos, sin)(2 pi u1) takes two uniform draws;
    numpy's own ``standard_normal`` calls the C library in its tails. Consumes
    ``gen.random(2 ceil(size / 2))``.

    Returns:
        float64 array of ``shape``.
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    size = int(np.prod(shape, dtype=np.int64))
    half = (size + 1) // 2
    u = gen.random((2, half))
    radius = np.sqrt(-2.0 * log(1.0 - u[0]))
    angle = (2.0 * _PI) * u[1]
    z = np.concatenate([radius * cos(angle), radius * sin(angle)])
    return z[:size].reshape(shape)
