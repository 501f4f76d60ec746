"""Elementary functions for the kernels' inner loops: exponentials and a logarithm that
vectorise.

A loop calling ``math.exp`` stays scalar (a libm call per element, 6-20 ns, slowest where
the result underflows). :func:`exp` is branch-free arithmetic that LLVM turns into SIMD
code: ``exp(x) = 2^k exp(r)``, ``k = round(x / ln 2)``, ``|r| <= ln(2) / 2`` (Cody-Waite
reduction with a two-part ln 2), the degree-13 Taylor polynomial of ``exp(r)`` in Estrin's
form (short dependency chains), and ``2^k`` built from its bits. Relative error at most
2 ulp; results below ``exp(-708)`` (under the smallest normal double) are 0, above
``exp(709)`` inf, NaN stays NaN.

:func:`exp32` is the single-precision form for the float32 likelihood (degree-7
polynomial, within 2 float32 ulp of the exact value; 0 below ``exp(-87)``, where float32
results stop being normal numbers, inf from ``exp(88)``): twice the SIMD lanes of
:func:`exp`.

:func:`log` is the logarithm of the same kind (a loop calling ``math.log`` stays scalar
too: the likelihood takes one per particle and group of satellites), within 1 ulp of the
exact value (libm's is within 0.52): libm's value, or its neighbour in 3 inputs in a
thousand (2e8 random inputs, float32 products and every binade).

:func:`sincos` is the sine and cosine of one argument of the same kind (a loop calling
``math.sin`` and ``math.cos`` stays scalar: 10-20 ns per call), within 1 ulp of the exact
values for ``|x| <= SINCOS_LARGEST`` (libm's, or its neighbour in 3 % of inputs: 2e6
random inputs at each of the scales 1, 4, 100, 1e4 and 4e5 rad, and the multiples of
pi / 4 up to 200 of them; the tests check every binade from 1e-9 rad): fdlibm's
reduction by pi / 2 in three parts (Cody-Waite; here each step's rounding error carried
exactly, with no branch) and its kernels ``__kernel_sin`` and ``__kernel_cos`` on the
reduced argument and its tail. :func:`sincos_into` fills arrays, falling back to libm
when an argument lies beyond that range.

:func:`largest` is the maximum of an array in four partial results (a loop into one
scalar waits on each comparison; these chains run side by side).

Inlined helpers are compiled into the kernels that call them, and numba's disk cache of a
kernel depends on its own file only: the package drops cached kernels older than any of
its sources at import (``kernels.drop_stale_caches``), so a change here recompiles them.
"""
from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from . import inline_kernel

_LOG2E = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01       # ln 2 to 32 bits: k * _LN2_HI is exact
_LN2_LO = 1.90821492927058770002e-10
_ROUND = 6755399441055744.0                # 1.5 * 2^52: adding it rounds to an integer
_LOWEST = -708.0                           # exp(-708) = 3.3e-308, above the smallest normal
_HIGHEST = 709.0


@intrinsic
def _bits_to_float(typingctx, bits):
    """The float64 whose IEEE bits are the int64 ``bits``."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


@intrinsic
def _float_to_bits(typingctx, value):
    """The IEEE bits of the float64 ``value`` as an int64."""
    sig = types.int64(types.float64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return sig, codegen


_ROUND_BITS = 0x4338000000000000           # the bits of _ROUND


@inline_kernel
def exp(x):
    """``e^x`` (float64), vectorisable; 0 below ``exp(-708)``, inf above ``exp(709)``."""
    y = x if x > _LOWEST else _LOWEST
    y = y if y < _HIGHEST else _HIGHEST
    shifted = y * _LOG2E + _ROUND
    k = shifted - _ROUND
    r = (y - k * _LN2_HI) - k * _LN2_LO
    r2 = r * r
    r4 = r2 * r2
    b0 = (1.0 + r) + (0.5 + r * (1.0 / 6.0)) * r2
    b1 = ((1.0 / 24.0) + r * (1.0 / 120.0)) + ((1.0 / 720.0) + r * (1.0 / 5040.0)) * r2
    b2 = (((1.0 / 40320.0) + r * (1.0 / 362880.0))
          + ((1.0 / 3628800.0) + r * (1.0 / 39916800.0)) * r2)
    b3 = (1.0 / 479001600.0) + r * (1.0 / 6227020800.0)
    p = (b0 + b1 * r4) + (b2 + b3 * r4) * (r4 * r4)
    # The low bits of ``shifted`` hold k: no float-to-integer conversion (AVX2 has none).
    out = p * _bits_to_float((_float_to_bits(shifted) - _ROUND_BITS + 1023) << 52)
    out = out if x > _LOWEST else 0.0
    out = out if x < _HIGHEST else np.inf
    return out if x == x else x


_SQRT_HALF_BITS = 0x3FE6A09E667F3BCD       # the bits of sqrt(1/2)
_SMALLEST_NORMAL = 2.2250738585072014e-308
_TWO_54 = 18014398509481984.0
#: ``2 / (2 n + 1)``, n = 1 .. 10: the series ``log(1 + f) = 2 atanh(s)``,
#: ``s = f / (2 + f)``, ``|s| <= 0.1716``: the first term left out is below 2^-60 of s.
_ATANH = tuple(2.0 / (2 * n + 1) for n in range(1, 11))


@inline_kernel
def log(x):
    """``log(x)`` (float64), vectorisable; within 1 ulp of libm's. -inf at 0, inf at
    inf, NaN below 0 and at NaN.

    ``x = 2^k m``, ``m`` in ``[sqrt(1/2), sqrt(2))`` from the bits (no float-to-integer
    conversion of the exponent); ``f = m - 1`` is exact, and
    ``log(1 + f) = f - f^2 / 2 + s (f^2 / 2 + R(s^2))`` with ``s = f / (2 + f)`` and
    ``R`` the rest of the atanh series: its rounding only enters a term ~f^3 / 12."""
    tiny = x < _SMALLEST_NORMAL
    y = x * _TWO_54 if tiny else x
    bits = _float_to_bits(y)
    k = (bits - _SQRT_HALF_BITS) >> 52
    m = _bits_to_float(bits - (k << 52))
    kf = np.float64(k) - (54.0 if tiny else 0.0)
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    z2 = z * z
    z4 = z2 * z2
    c1, c2, c3, c4, c5, c6, c7, c8, c9, c10 = _ATANH
    r = z * (((c1 + z * c2) + z2 * (c3 + z * c4))
             + z4 * ((c5 + z * c6) + z2 * (c7 + z * c8) + z4 * (c9 + z * c10)))
    hfsq = 0.5 * f * f
    out = kf * _LN2_HI + (f - (hfsq - (s * (hfsq + r) + kf * _LN2_LO)))
    out = out if x > 0.0 else (-np.inf if x == 0.0 else np.nan)
    return out if x < np.inf else x


# ----------------------------------------------------------------------- float32
_F32_LOG2E = np.float32(_LOG2E)
_F32_LN2_HI = np.float32(0.693145751953125)        # ln 2 to 16 bits: k * it is exact
_F32_LN2_LO = np.float32(1.428606765330187045e-06)
_F32_ROUND = np.float32(12582912.0)                 # 1.5 * 2^23
_F32_ROUND_BITS = 0x4B400000                        # its bits
_F32_LOWEST = np.float32(-87.0)                     # exp(-87) = 1.6e-38, a normal float32
_F32_HIGHEST = np.float32(88.0)
_F32_ONE = np.float32(1.0)
_F32_ZERO = np.float32(0.0)
_F32_INF = np.float32(np.inf)
_F32_TAYLOR = tuple(np.float32(1.0 / f) for f in (2.0, 6.0, 24.0, 120.0, 720.0, 5040.0))


@intrinsic
def _pow2_of_shifted32(typingctx, shifted):
    """``2^k`` (float32) from ``shifted = k + 1.5 * 2^23`` (float32, exact): the low bits
    of ``shifted`` hold k, moved into the exponent field in 32-bit integer arithmetic (in
    numba, int32 arithmetic would widen to int64 and stop the loop vectorising)."""
    sig = types.float32(types.float32)

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        k = builder.sub(builder.bitcast(args[0], i32), ir.Constant(i32, _F32_ROUND_BITS))
        biased = builder.add(k, ir.Constant(i32, 127))
        return builder.bitcast(builder.shl(biased, ir.Constant(i32, 23)), ir.FloatType())

    return sig, codegen


@inline_kernel
def exp32(x):
    """``e^x`` for a float32 ``x`` (float32), vectorisable; 0 below ``exp(-87)``, inf
    from ``exp(88)`` on (1.7e38, half the float32 range), NaN stays NaN."""
    y = x if x > _F32_LOWEST else _F32_LOWEST
    y = y if y < _F32_HIGHEST else _F32_HIGHEST
    shifted = y * _F32_LOG2E + _F32_ROUND
    k = shifted - _F32_ROUND
    r = (y - k * _F32_LN2_HI) - k * _F32_LN2_LO
    r2 = r * r
    c2, c3, c4, c5, c6, c7 = _F32_TAYLOR
    p = (_F32_ONE + r) + r2 * ((c2 + r * c3) + r2 * ((c4 + r * c5) + r2 * (c6 + r * c7)))
    out = p * _pow2_of_shifted32(shifted)
    out = out if x > _F32_LOWEST else _F32_ZERO
    out = out if x < _F32_HIGHEST else _F32_INF
    return out if x == x else x


# ------------------------------------------------------------------ sine, cosine
#: Largest ``|x|`` of :func:`sincos` (``k * _PIO2_1`` stays exact for ``|k| < 2^20``).
SINCOS_LARGEST = 2.0 ** 18
_INV_PIO2 = 6.36619772367581382433e-01
# pi / 2 in 33-bit parts (fdlibm's pio2_1, pio2_2, pio2_3) and the rest: k times a part is
# exact for |k| < 2^20.
_PIO2_1 = 1.57079632673412561417e+00
_PIO2_2 = 6.07710050630396597660e-11
_PIO2_3 = 2.02226624871116645580e-21
_PIO2_3T = 8.47842766036889956997e-32
# fdlibm's __kernel_sin and __kernel_cos coefficients on [-pi / 4, pi / 4].
_SIN = (-1.66666666666666324348e-01, 8.33333333332248946124e-03,
        -1.98412698298579493134e-04, 2.75573137070700676789e-06,
        -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_COS = (4.16666666666666019037e-02, -1.38888888888741095749e-03,
        2.48015872894767294178e-05, -2.75573143513906633035e-07,
        2.08757232129817482790e-09, -1.13596475577881948265e-11)


@inline_kernel
def _two_diff(a, b):
    """``a - b`` and its rounding error, exactly (Knuth's TwoSum, no branch)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


@inline_kernel
def sincos(x):
    """``(sin x, cos x)`` (float64), vectorisable, for ``|x| <= SINCOS_LARGEST``; NaN for
    NaN and infinite ``x``."""
    shifted = x * _INV_PIO2 + _ROUND
    k = shifted - _ROUND
    a = x - k * _PIO2_1                      # exact (Sterbenz)
    b, e1 = _two_diff(a, k * _PIO2_2)
    c, e2 = _two_diff(b, k * _PIO2_3)
    tail = (e1 + e2) - k * _PIO2_3T
    # x - k pi / 2 = y0 + y1, |y0| <= pi / 4 (a zero tail keeps the sign of a zero c).
    y0 = c + tail if tail != 0.0 else c
    y1 = (c - y0) + tail
    quadrant = _float_to_bits(shifted) - _ROUND_BITS
    s1, s2, s3, s4, s5, s6 = _SIN
    c1, c2, c3, c4, c5, c6 = _COS
    z = y0 * y0
    v = z * y0
    rs = s2 + z * (s3 + z * (s4 + z * (s5 + z * s6)))
    sin_y = y0 - ((z * (0.5 * y1 - v * rs) - y1) - v * s1)
    zz = z * z
    rc = z * (c1 + z * (c2 + z * c3)) + zz * zz * (c4 + z * (c5 + z * c6))
    hz = 0.5 * z
    w = 1.0 - hz
    cos_y = w + (((1.0 - w) - hz) + (z * rc - y0 * y1))
    odd = (quadrant & 1) != 0
    sin_x = cos_y if odd else sin_y
    cos_x = sin_y if odd else cos_y
    sin_x = -sin_x if (quadrant & 2) != 0 else sin_x
    cos_x = -cos_x if ((quadrant + 1) & 2) != 0 else cos_x
    return sin_x, cos_x


@inline_kernel
def sincos_into(x, sin_out, cos_out):
    """``sin_out[i], cos_out[i] = sin x[i], cos x[i]`` over the (N,) ``x``: :func:`sincos`
    where every ``|x|`` is within ``SINCOS_LARGEST`` (a NaN is too: it stays NaN),
    libm's otherwise."""
    n = x.shape[0]
    beyond = False
    for i in range(n):
        beyond |= abs(x[i]) > SINCOS_LARGEST
    if beyond:
        for i in range(n):
            sin_out[i] = math.sin(x[i])
            cos_out[i] = math.cos(x[i])
        return
    for i in range(n):
        s, c = sincos(x[i])
        sin_out[i] = s
        cos_out[i] = c


@inline_kernel
def largest(values, initial):
    """The largest of ``initial`` and the (N,) ``values``, in four partial maxima."""
    n = values.shape[0]
    stop = n - n % 4
    m0 = m1 = m2 = m3 = initial
    for i in range(0, stop, 4):
        m0 = max(m0, values[i])
        m1 = max(m1, values[i + 1])
        m2 = max(m2, values[i + 2])
        m3 = max(m3, values[i + 3])
    for i in range(stop, n):
        m0 = max(m0, values[i])
    return max(max(m0, m1), max(m2, m3))
