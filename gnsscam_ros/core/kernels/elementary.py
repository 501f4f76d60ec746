"""Elementary functions for the kernels' inner loops: an exponential that vectorises.

A loop calling ``math.exp`` stays scalar (a libm call per element, 6-20 ns, slowest where
the result underflows). :func:`exp` is branch-free arithmetic that LLVM turns into SIMD
code: ``exp(x) = 2^k exp(r)``, ``k = round(x / ln 2)``, ``|r| <= ln(2) / 2`` (Cody-Waite
reduction with a two-part ln 2), the degree-13 Taylor polynomial of ``exp(r)`` in Estrin's
form (short dependency chains), and ``2^k`` built from its bits. Relative error at most
2 ulp; results below ``exp(-708)`` (under the smallest normal double) are 0, above
``exp(709)`` inf, NaN stays NaN.

Inlined helpers are compiled into the kernels that call them, and numba's disk cache of a
kernel depends on its own file only: the package drops cached kernels older than any of
its sources at import (``kernels.drop_stale_caches``), so a change here recompiles them.
"""
from __future__ import annotations

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
