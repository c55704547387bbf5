"""A compiled ``exp`` of non-positive arguments that vectorises (SIMD) inside numba loops.

numba calls the C library's scalar ``exp`` unless Intel's SVML is present, so a loop
over the line-of-sight mixture's components (:mod:`mavispm.dynamics.line_of_sight`)
cannot use the CPU's vector units. :func:`exp_nonpositive` is the textbook
Cody-Waite range reduction with a polynomial (Muller, *Elementary Functions*, 2016,
ch. 11): ``x = n ln 2 + r`` with ``|r| <= ln 2 / 2``, ``exp(r)`` by its Taylor
polynomial of degree 12 (truncation < 2e-16 relative), and ``2^n`` built in the
exponent bits. Every step is branch-free, so LLVM vectorises loops that call it.

Arguments below -708 (``exp`` < 3.3e-308, the smallest normal double's scale) return
``exp(-708)``: callers that sum such terms must treat a total below ~1e-280 as
underflowed and fall back to a log-sum-exp (as the mixture does). NaN propagates.
Measured on [-708, 0]: relative error <= 4.7e-16 against mpmath, <= 4.5e-16 against
``numpy.exp`` (``tests/test_dynamics_vector_exp.py``).
"""

from __future__ import annotations

import math

import llvmlite.ir as llir
import numba
from numba import types
from numba.extending import intrinsic

__all__ = ["exp_nonpositive"]

_LOG2E = 1.4426950408889634
#: ln 2 split in a part exact in 32 bits and the rest (Cody & Waite 1980).
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds to an integer held in the low mantissa bits.
_SHIFT = 6755399441055744.0
_LEAST = -708.0
_C = tuple(1.0 / math.factorial(k) for k in range(13))
_C0, _C1, _C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11, _C12 = _C


@intrinsic
def _bits_of(typingctx, x):  # pragma: no cover - compiled
    """The 64 bits of a double as an int64 (no conversion)."""
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], llir.IntType(64))

    return types.int64(types.float64), codegen


@intrinsic
def _double_of(typingctx, bits):  # pragma: no cover - compiled
    """The double whose 64 bits are ``bits`` (no conversion)."""
    if not isinstance(bits, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], llir.DoubleType())

    return types.float64(types.int64), codegen


@numba.njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def exp_nonpositive(x):  # pragma: no cover - compiled
    """``exp(x)`` for ``x <= 0`` (relative error < 5e-16; ``x < -708`` gives ``exp(-708)``).

    Parameters
    ----------
    x : float
        Argument (<= 0; positive values up to ~700 work but are not the intended use).

    Returns
    -------
    float
    """
    x = max(x, _LEAST)
    shifted = x * _LOG2E + _SHIFT
    n = shifted - _SHIFT  # round(x / ln 2), exactly
    r = (x - n * _LN2_HI) - n * _LN2_LO
    p = _C12
    p = p * r + _C11
    p = p * r + _C10
    p = p * r + _C9
    p = p * r + _C8
    p = p * r + _C7
    p = p * r + _C6
    p = p * r + _C5
    p = p * r + _C4
    p = p * r + _C3
    p = p * r + _C2
    p = p * r + _C1
    p = p * r + _C0
    return p * _double_of((_bits_of(shifted) + 1023) << 52)
