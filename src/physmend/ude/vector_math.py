"""The network's activations and their derivatives for the compiled loops, with no call into the C
library (numba).

A call into the C library (``exp``, ``log1p``, ``erf``) cannot be vectorised: a loop over a layer's
width that calls one runs one value at a time, at 20–40 ns each, and softplus and gelu networks
trained at half the speed of tanh ones. Written here from multiplications, additions, divisions and
selections, a loop over a layer compiles to vector instructions. Each function is within a few units
in the last place of the exact value (``tests/ude/test_vector_math.py``), keeps NaN, and gives the
limits at ±infinity. Arguments of another dtype (float32) are computed in float64.

- ``e^y`` (:func:`exp_pos`, ``0 ≤ y``): ``2^k·e^r·e^{-c}``, ``r = y - k·ln2_hi`` exact and ``c =
  k·ln2_lo`` (Cody and Waite's two parts of ``ln 2``), ``e^r`` by its series to ``r¹⁴/14!``, ``2^k`` the
  double whose exponent field is ``k + 1023`` (its bits written directly, two integer operations: as a
  product of ten powers of two chosen by the bits of ``k``, the same value, it was half of ``e^y``'s
  work); infinity from ``y = 708`` on (``e^708 ≈ 3e307``; the C library's overflow is at 709.78).
- ``tanh``: Cephes' rational form below 0.625, else ``1 - 2/(e^{2|x|} + 1)``.
- ``sigmoid``: ``1/(E+1)`` (``a < 0``) or ``1 - 1/(E+1)``, ``E = e^{|a|}``.
- ``softplus``: ``max(a, 0) + log1p(e^{-|a|})``, ``log1p(z) = 2·atanh(z/(2+z))`` by its series
  (``z/(2+z) ≤ 1/3``, 18 terms); ``a`` itself above 20, as torch.
- ``erf``: ``x·P(x²)`` below 1.5; ``1 - e^{-x²}·Q(1/x)/x`` from 1.5 to 6; 1 beyond (``erf(6) = 1 -
  2e-17``). ``P`` (degree 15) and ``Q`` (degree 19) are Chebyshev fits at 50 digits,
  ``mpmath.chebyfit(lambda t: erf(√t)/√t, [0, 2.25], 16)`` and ``mpmath.chebyfit(lambda u:
  erfc(1/u)·e^{1/u²}/u, [1/6, 1/1.5], 20)``, rounded to doubles. ``e^{-x²}`` is exact to
  ``x²`` units in the last place (``x²`` is rounded), as the C library's ``exp(-x*x)``.

numba's cache keys each compiled function on the contents of its own file: the loops that inline
these recompile when their own files change, not when this one does. After editing this module,
delete the cache files (``__pycache__/*.nbi``, ``*.nbc`` beside it); touching a file does not
recompile it.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

FAST = {"reassoc", "contract", "nsz"}
"""The fast-math flags of the compiled loops: reassociation and contraction only (NaN and infinity
keep their meaning)."""

_SQRT_HALF = 0.5**0.5
_INV_SQRT_2PI = (2.0 * math.pi) ** -0.5
_EXP_MAX = 708.0

# Cephes' tanh for |x| < 0.625: x + x·z·P(z)/Q(z), z = x² (relative error ≤ 2.5e-16)
_P0, _P1, _P2 = -9.64399179425052238628e-1, -9.92877231001918586564e1, -1.61468768441708447952e3
_Q0, _Q1, _Q2 = 1.12811678491632931402e2, 2.23548839060100448583e3, 4.84406305325125486048e3
_LN2_HI, _LN2_LO, _INV_LN2 = 6.93147180369123816490e-01, 1.90821492927058770002e-10, 1.44269504088896338700e00
_E = tuple(1.0 / math.factorial(j) for j in range(15))  # e^r's series: 1/j!


@intrinsic
def _as_double(typingctx, bits):  # noqa: ANN001, ANN202, ARG001 - numba's intrinsic signature
    """The double whose 64 bits are the integer ``bits`` (int64), as C's ``memcpy`` between the two."""
    if bits != types.int64:
        return None

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202, ARG001
        return builder.bitcast(args[0], context.get_value_type(types.float64))

    return types.float64(types.int64), codegen


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def exp_pos(y: float) -> float:  # pragma: no cover - compiled
    """``e^y`` for ``y ≥ 0``; infinity from 708 on."""
    held = y if y < _EXP_MAX else _EXP_MAX
    k = np.int64(held * _INV_LN2 + 0.5)
    r = held - k * _LN2_HI  # exact: k·ln2_hi has at most 42 bits, and r is within ln 2 of 0
    c = k * _LN2_LO  # below 2e-7: e^{-c} by three terms, as a factor (as a term of r, the fast-math
    # flags let the compiler add k·ln2_hi and k·ln2_lo first, off by up to 200 units in the last place)
    e = _E[14]
    e = _E[13] + r * e
    e = _E[12] + r * e
    e = _E[11] + r * e
    e = _E[10] + r * e
    e = _E[9] + r * e
    e = _E[8] + r * e
    e = _E[7] + r * e
    e = _E[6] + r * e
    e = _E[5] + r * e
    e = _E[4] + r * e
    e = _E[3] + r * e
    e = _E[2] + r * e
    e = _E[1] + r * e
    e = _E[0] + r * e
    e = e * (1.0 - c * (1.0 - 0.5 * c))
    p = _as_double((k + 1023) << 52)  # 2^k, exactly (0 ≤ k ≤ 1021)
    out = p * e if y < _EXP_MAX else math.inf
    return out if y == y else y


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def tanh(x: float) -> float:  # pragma: no cover - compiled
    """tanh (3 ns against the C library's 23 ns per value here); at most 2 units in the last place
    from the C library's (torch's own: 2), 1 beyond |x| = 20."""
    ax = abs(x)
    z = x * x
    small = x + x * z * (((_P0 * z + _P1) * z + _P2) / (((z + _Q0) * z + _Q1) * z + _Q2))
    big = 1.0 - 2.0 / (exp_pos(2.0 * ax if ax < 20.0 else 40.0) + 1.0)
    big = big if x >= 0.0 else -big
    out = small if ax < 0.625 else big
    return out if x == x else x


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def sigmoid(a: float) -> float:  # pragma: no cover - compiled
    """``1/(1 + e^{-a})``."""
    small = 1.0 / (exp_pos(abs(a)) + 1.0)  # sigmoid(-|a|)
    out = 1.0 - small if a >= 0.0 else small
    return out if a == a else a


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def softplus(a: float) -> float:  # pragma: no cover - compiled
    """``log(1 + e^a)``, ``a`` itself above 20 (torch's threshold)."""
    s = 1.0 / (2.0 * exp_pos(abs(a)) + 1.0)  # z/(2+z), z = e^{-|a|}
    t = s * s
    q = 1.0 / 35
    q = q * t + 1.0 / 33
    q = q * t + 1.0 / 31
    q = q * t + 1.0 / 29
    q = q * t + 1.0 / 27
    q = q * t + 1.0 / 25
    q = q * t + 1.0 / 23
    q = q * t + 1.0 / 21
    q = q * t + 1.0 / 19
    q = q * t + 1.0 / 17
    q = q * t + 1.0 / 15
    q = q * t + 1.0 / 13
    q = q * t + 1.0 / 11
    q = q * t + 1.0 / 9
    q = q * t + 1.0 / 7
    q = q * t + 1.0 / 5
    q = q * t + 1.0 / 3
    q = q * t + 1.0 / 1
    out = (a if a > 0.0 else 0.0) + 2.0 * s * q
    out = a if a > 20.0 else out
    return out if a == a else a


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def erf_and_gauss(x: float) -> tuple[float, float]:  # pragma: no cover - compiled
    """``(erf(x), e^{-x²})``."""
    ax = abs(x)
    z = x * x
    gauss = 1.0 / exp_pos(z)
    inv = 1.0 / (ax if ax > 1.0 else 1.0)
    # erf(x)/x = P(x²) on 0 ≤ x ≤ 1.5 (highest power first)
    p = -9.854893631973009e-15
    p = p * z + 3.2537896660097213e-13
    p = p * z + -6.1758411722331915e-12
    p = p * z + 9.257929022544438e-11
    p = p * z + -1.2254075631992835e-09
    p = p * z + 1.4801276360093684e-08
    p = p * z + -1.6365135951628023e-07
    p = p * z + 1.6462051744758016e-06
    p = p * z + -1.4925646319299433e-05
    p = p * z + 0.00012055332795419675
    p = p * z + -0.0008548327017499108
    p = p * z + 0.005223977625317255
    p = p * z + -0.026866170645115376
    p = p * z + 0.11283791670955019
    p = p * z + -0.3761263890318375
    p = p * z + 1.1283791670955126
    small = ax * p
    # erfc(x)·e^{x²}·x = Q(1/x) on 1.5 ≤ x ≤ 6
    q = 8.229986025147957
    q = q * inv + -68.19102821770288
    q = q * inv + 264.0506109109315
    q = q * inv + -632.9969610623649
    q = q * inv + 1047.6834238925321
    q = q * inv + -1261.2662789886424
    q = q * inv + 1128.841391243727
    q = q * inv + -748.3765936925781
    q = q * inv + 352.5487681706663
    q = q * inv + -101.93549743542026
    q = q * inv + 5.802098664225173
    q = q * inv + 8.036065099792234
    q = q * inv + -2.1055480835117675
    q = q * inv + -0.5129719885512356
    q = q * inv + -0.09618686840096967
    q = q * inv + 0.435297546615886
    q = q * inv + -0.0010926982612743125
    q = q * inv + -0.2820280117951816
    q = q * inv + -2.496672572095589e-06
    q = q * inv + 0.5641896267375814
    large = 1.0 - gauss * inv * q
    out = small if ax < 1.5 else (large if ax < 6.0 else 1.0)
    out = out if x >= 0.0 else -out
    return (out if x == x else x), gauss


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def gelu(a: float) -> float:  # pragma: no cover - compiled
    """``a·Φ(a) = a/2·(1 + erf(a/√2))``."""
    return 0.5 * a * (1.0 + erf_and_gauss(a * _SQRT_HALF)[0])


@numba.njit(cache=True, fastmath=FAST, inline="always", error_model="numpy")
def gelu_derivative(a: float) -> float:  # pragma: no cover - compiled
    """``Φ(a) + a·φ(a)``."""
    erf, gauss = erf_and_gauss(a * _SQRT_HALF)
    return 0.5 * (1.0 + erf) + a * gauss * _INV_SQRT_2PI

