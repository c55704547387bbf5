"""A compiled ``exp`` and ``log`` that vectorise (SIMD) inside numba loops.

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
``numpy.exp`` (``tests/test_dynamics_vector_exp.py``). :func:`exp_bounded` is the same
function for arguments of either sign (clamped to [-708, 709]).

:func:`log_positive` is the natural logarithm of fdlibm's ``e_log.c`` (Sun Microsystems
1993; the algorithm of musl and FreeBSD): ``x = 2^k (1 + f)`` with ``1 + f`` in
[sqrt(2)/2, sqrt(2)), ``s = f / (2 + f)``, ``log(1 + f) = f - s (f - R(s^2))`` with
fdlibm's degree-14 minimax polynomial ``R`` (error < 1 ulp), and ``k ln 2`` added in
Cody-Waite halves. The exponent and mantissa are taken from the bits and every step is
branch-free (special arguments are selected at the end: 0 gives ``-inf``, negative
numbers and NaN give NaN, ``+inf`` gives ``+inf``; subnormal numbers are scaled by
``2^54`` first), so loops that call it vectorise. Measured against mpmath and numpy:
``tests/test_dynamics_vector_exp.py``.
"""

from __future__ import annotations

import math

import llvmlite.ir as llir
import numba
from numba import types
from numba.extending import intrinsic

__all__ = ["exp_bounded", "exp_nonpositive", "log_positive"]

_LOG2E = 1.4426950408889634
#: ln 2 split in a part exact in 32 bits and the rest (Cody & Waite 1980).
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
#: 1.5 * 2^52: adding it rounds to an integer held in the low mantissa bits.
_SHIFT = 6755399441055744.0
_LEAST = -708.0
#: Largest argument of :func:`exp_bounded` (``2^n`` stays a normal double).
_MOST = 709.0
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
def _exp_reduced(x):  # pragma: no cover - compiled
    """``exp(x)`` for ``-708 <= x <= 709`` (the callers clamp; NaN propagates)."""
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
    return _exp_reduced(max(x, _LEAST))


@numba.njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def exp_bounded(x):  # pragma: no cover - compiled
    """``exp(x)`` clamped to ``[exp(-708), exp(709)]`` (relative error < 5e-16 inside).

    Parameters
    ----------
    x : float
        Argument (below -708 it is taken as -708, above 709 as 709; NaN propagates).

    Returns
    -------
    float
    """
    return _exp_reduced(min(max(x, _LEAST), _MOST))


#: fdlibm e_log.c: ln 2 in two parts and the minimax coefficients of R(s^2).
_LG1 = 6.666666666666735130e-01
_LG2 = 3.999999999940941908e-01
_LG3 = 2.857142874366239149e-01
_LG4 = 2.222219843214978396e-01
_LG5 = 1.818357216161805012e-01
_LG6 = 1.531383769920937332e-01
_LG7 = 1.479819860511658591e-01
_TINY = 2.2250738585072014e-308
_TWO54 = 18014398509481984.0
#: ``0x3ff00000 - 0x3fe6a09e`` (the high word of sqrt(2)/2) in the high 32 bits
_SQRT_HALF_SHIFT = (0x3FF00000 - 0x3FE6A09E) << 32
_SQRT_HALF_HIGH = 0x3FE6A09E << 32
_MANTISSA = 0x000FFFFFFFFFFFFF


@numba.njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def log_positive(x):  # pragma: no cover - compiled
    """Natural logarithm, branch-free (fdlibm's algorithm; see the module notes).

    Parameters
    ----------
    x : float
        Argument (> 0; 0 gives ``-inf``, negative and NaN give NaN, ``+inf`` gives
        ``+inf``).

    Returns
    -------
    float
    """
    sub = x < _TINY
    y = x * _TWO54 if sub else x
    bits = _bits_of(y) + _SQRT_HALF_SHIFT
    k = (bits >> 52) - (1023 + 54 if sub else 1023)
    m = _double_of((bits & _MANTISSA) + _SQRT_HALF_HIGH)
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    t1 = w * (_LG2 + w * (_LG4 + w * _LG6))
    t2 = z * (_LG1 + w * (_LG3 + w * (_LG5 + w * _LG7)))
    r = t2 + t1
    hfsq = 0.5 * f * f
    dk = float(k)
    out = dk * _LN2_HI - ((hfsq - (s * (hfsq + r) + dk * _LN2_LO)) - f)
    out = out if x < math.inf else x  # +inf (and NaN, kept below)
    out = -math.inf if x == 0.0 else out
    return out if x >= 0.0 else math.nan
