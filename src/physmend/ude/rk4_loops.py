"""The loops of :mod:`physmend.ude.adjoint`'s RK4 solve, compiled (numba): forward and backward.

Eager PyTorch pays a few microseconds per operation, and the RK4 recursion of a small hybrid model
is about a hundred operations per step, each on a few hundred numbers. Here each row (one segment
of one model) runs its whole time loop as one compiled loop: its state, its matrix ``A`` and its
network's stages stay in cache, and nothing is dispatched per operation. The rows are independent,
so they run one after another.

Layout (one dtype throughout, C-contiguous, rows model-major ``r = m·S + s``):

- ``u0 (R, n)``; ``At (R, n, n)`` each row's ``Aᵀ`` (forward) and ``A (R, n, n)`` (backward);
  ``d (H, R, n)`` the drives at the ``H = 2K+1`` half steps; ``pre (H, M, S, w₀)`` the network's
  first layer on inputs and parameters; ``wu (M, r, w₀)`` its weights on the states it reads;
- ``W (L, M, P, P)``, ``b (L, M, P)``: the layers after the first, zero-padded to ``P``; layer
  ``l`` maps width ``dims[l]`` to ``dims[l+1]``; the last (``l = L-1``) is the output layer
  (width ``k``, no activation), stored transposed (``W[L-1, m, c, q]``);
- ``gain (R, k)``; ``reads (r,)``, ``index (k,)`` the state columns the network reads and the
  ones it corrects; ``lo, hi (R, n)`` the box when ``boxed``.

Forward writes the grid points ``traj (K+1, R, n)`` and, per stage ``t = 4k + s``, the state it
evaluated ``Vs (R, T, n)``, each activated layer's pre-activation and value ``Z, Y (L, R, T, P)``,
the network's output ``OUT (R, T, k)`` and, per clamp, 1 where the state was inside the box
``MASK (R, T, n)`` (clamp ``4k+s`` holds stage ``s+2``'s state, the last one step ``k``'s end).

Backward, from ``grad (K+1, R, n)``, writes ``g_u0 (R, n)``, what each stage's right-hand side
received ``G (R, T, n)``, the gradient of every layer's pre-activation ``GA (L+1, R, T, P)`` (the
output layer's at ``L``), and the sums over stages that belong to one half step or one row:
``g_d (H, R, n)``, ``g_pre (H, M, S, w₀)``, ``g_gain (R, k)``. The weight and matrix gradients are
products over all stages of these, taken in :mod:`physmend.ude.compiled_solve`.

Activations are numbered as :data:`CODES`, one per model (``codes (M,)``, row ``r`` model ``r // S``'s:
:func:`physmend.ude.compiled_solve.codes`), so models with different activations are one solve.
NaN and infinity pass through as in torch (the fast math flags allow reassociation only).
"""

from __future__ import annotations

import math

import numba
import numpy as np

#: the activations written here, by the number the loops take
CODES = {"tanh": 0, "sigmoid": 1, "relu": 2, "softplus": 3, "silu": 4, "elu": 5, "gelu": 6}
_FAST = {"reassoc", "contract", "nsz"}

_SQRT_HALF = 0.5**0.5
_INV_SQRT_2PI = (2.0 * math.pi) ** -0.5


# Cephes' tanh for |x| < 0.625: x + x·z·P(z)/Q(z), z = x² (relative error ≤ 2.5e-16)
_P0, _P1, _P2 = -9.64399179425052238628e-1, -9.92877231001918586564e1, -1.61468768441708447952e3
_Q0, _Q1, _Q2 = 1.12811678491632931402e2, 2.23548839060100448583e3, 4.84406305325125486048e3
# e^y = 2^k·e^r, r = y - k·ln 2 in two parts (Cody and Waite), e^r by its series to r¹⁴/14!
_LN2_HI, _LN2_LO, _INV_LN2 = 6.93147180369123816490e-01, 1.90821492927058770002e-10, 1.44269504088896338700e00
_E0 = 1.0
_E1 = 1.0
_E2 = 1.0 / 2
_E3 = 1.0 / 6
_E4 = 1.0 / 24
_E5 = 1.0 / 120
_E6 = 1.0 / 720
_E7 = 1.0 / 5040
_E8 = 1.0 / 40320
_E9 = 1.0 / 362880
_E10 = 1.0 / 3628800
_E11 = 1.0 / 39916800
_E12 = 1.0 / 479001600
_E13 = 1.0 / 6227020800
_E14 = 1.0 / 87178291200


@numba.njit(cache=True, fastmath=_FAST, inline="always", error_model="numpy")
def _tanh(x: float) -> float:  # pragma: no cover - compiled
    """tanh with no call into the C library, so that a loop of it compiles to vector instructions
    (3 ns against the C library's 23 ns per value here): Cephes' rational form below 0.625, else
    ``1 - 2/(e^{2|x|} + 1)``, ``e^y = 2^k·e^r`` with ``2^k`` a product of exact powers of two chosen by
    the bits of ``k``. At most 2 units in the last place from the C library's (torch's own: 2),
    1 beyond |x| = 20, NaN kept."""
    ax = abs(x)
    z = x * x
    small = x + x * z * (((_P0 * z + _P1) * z + _P2) / (((z + _Q0) * z + _Q1) * z + _Q2))
    y = 2.0 * ax if ax < 20.0 else 40.0
    k = np.int64(y * _INV_LN2 + 0.5)
    r = (y - k * _LN2_HI) - k * _LN2_LO
    e = _E14
    e = _E13 + r * e
    e = _E12 + r * e
    e = _E11 + r * e
    e = _E10 + r * e
    e = _E9 + r * e
    e = _E8 + r * e
    e = _E7 + r * e
    e = _E6 + r * e
    e = _E5 + r * e
    e = _E4 + r * e
    e = _E3 + r * e
    e = _E2 + r * e
    e = _E1 + r * e
    e = _E0 + r * e
    p = 2.0 if k & 1 else 1.0
    p = p * (4.0 if k & 2 else 1.0)
    p = p * (16.0 if k & 4 else 1.0)
    p = p * (256.0 if k & 8 else 1.0)
    p = p * (65536.0 if k & 16 else 1.0)
    p = p * (4294967296.0 if k & 32 else 1.0)
    p = p * (18446744073709551616.0 if k & 64 else 1.0)
    big = 1.0 - 2.0 / (p * e + 1.0)
    big = big if x >= 0.0 else -big
    out = small if ax < 0.625 else big
    return out if x == x else x


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def _activate(code, Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``Y[l, r, t, :width] = act(Z[l, r, t, :width])``, one loop per activation (each compiles to
    vector instructions). The loops index whole arrays: a slice would be a new array each time."""
    if code == 0:
        for c in range(width):
            Y[l, r, t, c] = _tanh(Z[l, r, t, c])
    else:
        for c in range(width):
            Y[l, r, t, c] = _act(code, Z[l, r, t, c])


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def _times_derivative(code, Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``GA[l, r, t, :width] *= act'(Z[l, r, t, :width])`` (``Y`` the activation's values)."""
    if code == 0:
        for c in range(width):
            y = Y[l, r, t, c]
            GA[l, r, t, c] *= 1.0 - y * y
    else:
        for c in range(width):
            GA[l, r, t, c] *= _dact(code, Z[l, r, t, c], Y[l, r, t, c])


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _act(code: int, a: float) -> float:  # pragma: no cover - compiled
    if code == 0:
        return _tanh(a)
    if code == 1:
        return 1.0 / (1.0 + math.exp(-a))
    if code == 2:
        return a if a > 0.0 or a != a else 0.0
    if code == 3:
        return a if a > 20.0 else math.log1p(math.exp(a))
    if code == 4:
        return a / (1.0 + math.exp(-a))
    if code == 5:
        return a if a > 0.0 else math.expm1(a)
    return 0.5 * a * (1.0 + math.erf(a * _SQRT_HALF))


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _dact(code: int, a: float, y: float) -> float:  # pragma: no cover - compiled
    if code == 0:
        return 1.0 - y * y
    if code == 1:
        return y * (1.0 - y)
    if code == 2:
        return 1.0 if a > 0.0 else 0.0
    if code == 3:
        return 1.0 / (1.0 + math.exp(-a))
    if code == 4:
        s = 1.0 / (1.0 + math.exp(-a))
        return s * (1.0 + a * (1.0 - s))
    if code == 5:
        return 1.0 if a > 0.0 else y + 1.0
    return 0.5 * (1.0 + math.erf(a * _SQRT_HALF)) + a * math.exp(-0.5 * a * a) * _INV_SQRT_2PI


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _rhs(r, t, i, Vs, du, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover
    """``du = f(Vs[r, t])`` for row ``r`` at stage ``t`` (half step ``i``), keeping the stage's layers."""
    m = r // S
    s = r - m * S
    n = du.shape[0]
    L = W.shape[0]
    w0 = dims[0]
    for c in range(w0):
        Z[0, r, t, c] = pre[i, m, s, c]
    for q in range(reads.shape[0]):
        vq = Vs[r, t, reads[q]]
        for c in range(w0):
            Z[0, r, t, c] += vq * wu[m, q, c]
    _activate(code, Z, Y, 0, r, t, w0)
    for l in range(L - 1):
        a_in, a_out = dims[l], dims[l + 1]
        for c in range(a_out):
            Z[l + 1, r, t, c] = b[l, m, c]
        for q in range(a_in):
            yq = Y[l, r, t, q]
            for c in range(a_out):
                Z[l + 1, r, t, c] += yq * W[l, m, q, c]
        _activate(code, Z, Y, l + 1, r, t, a_out)
    a_in, k = dims[L - 1], dims[L]
    for c in range(k):
        acc = 0.0
        for q in range(a_in):
            acc += W[L - 1, m, c, q] * Y[L - 1, r, t, q]
        OUT[r, t, c] = b[L - 1, m, c] + acc
    for e in range(n):
        du[e] = d[i, r, e]
    for j in range(n):
        vj = Vs[r, t, j]
        for e in range(n):
            du[e] += vj * At[r, j, e]
    for c in range(k):
        du[index[c]] += OUT[r, t, c] * gain[r, c]


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def _stage(r, t, c, alpha, du, boxed, lo, hi, Vs, MASK):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``Vs[r, c+1] = Vs[r, t] + alpha·du`` held in row ``r``'s box, recording clamp ``c``'s mask."""
    for e in range(du.shape[0]):
        val = Vs[r, t, e] + alpha * du[e]
        if boxed:
            MASK[r, c, e] = 1.0 if (val >= lo[r, e] and val <= hi[r, e]) else 0.0
            if val < lo[r, e]:
                val = lo[r, e]
            elif val > hi[r, e]:
                val = hi[r, e]
        Vs[r, c + 1, e] = val


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _forward_row(r, h, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, boxed, lo, hi,  # noqa: ANN001, ANN202, PLR0913
                 traj, Vs, Z, Y, OUT, MASK):  # pragma: no cover - compiled
    code = codes[r // S]
    n = u0.shape[1]
    steps = traj.shape[0] - 1
    k1 = np.empty(n, u0.dtype)
    k2 = np.empty(n, u0.dtype)
    k3 = np.empty(n, u0.dtype)
    k4 = np.empty(n, u0.dtype)
    for e in range(n):
        traj[0, r, e] = u0[r, e]
    for kk in range(steps):
        t = 4 * kk
        for e in range(n):
            Vs[r, t, e] = traj[kk, r, e]
        _rhs(r, t, 2 * kk, Vs, k1, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT)
        _stage(r, t, t, 0.5 * h, k1, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 1, 2 * kk + 1, Vs, k2, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT)
        _stage(r, t, t + 1, 0.5 * h, k2, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 2, 2 * kk + 1, Vs, k3, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT)
        _stage(r, t, t + 2, h, k3, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 3, 2 * kk + 2, Vs, k4, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT)
        h6 = h / 6.0
        for e in range(n):
            val = Vs[r, t, e] + h6 * ((k1[e] + 2.0 * (k2[e] + k3[e])) + k4[e])
            if boxed:
                MASK[r, t + 3, e] = 1.0 if (val >= lo[r, e] and val <= hi[r, e]) else 0.0
                if val < lo[r, e]:
                    val = lo[r, e]
                elif val > hi[r, e]:
                    val = hi[r, e]
            traj[kk + 1, r, e] = val


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def forward(h, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, boxed, lo, hi,  # noqa: ANN001, ANN201, PLR0913
            traj, Vs, Z, Y, OUT, MASK):  # pragma: no cover - compiled
    for r in range(u0.shape[0]):
        _forward_row(r, h, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, boxed, lo, hi,
                     traj, Vs, Z, Y, OUT, MASK)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", parallel=True)
def forward_threads(h, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, boxed, lo, hi,  # noqa: ANN001, ANN201, PLR0913
                    traj, Vs, Z, Y, OUT, MASK):  # pragma: no cover - compiled
    """:func:`forward` with the rows shared among numba's threads."""
    for r in numba.prange(u0.shape[0]):
        _forward_row(r, h, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, boxed, lo, hi,
                     traj, Vs, Z, Y, OUT, MASK)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _vjp(r, t, G, gv, A, wu, W, dims, gain, reads, index, code, S, Z, Y, GA):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover
    """``gv = J_f(Vs[r, t])ᵀ G[r, t]`` for row ``r`` at stage ``t``, keeping each layer's ``∂pre-activation``."""
    m = r // S
    n = gv.shape[0]
    L = W.shape[0]
    k = dims[L]
    for c in range(k):
        GA[L, r, t, c] = G[r, t, index[c]] * gain[r, c]
    for l in range(L - 1, -1, -1):
        a_in, a_out = dims[l], dims[l + 1]
        if l == L - 1:  # the output layer, stored transposed
            for q in range(a_in):
                GA[l, r, t, q] = 0.0
            for c in range(a_out):
                uc = GA[l + 1, r, t, c]
                for q in range(a_in):
                    GA[l, r, t, q] += uc * W[l, m, c, q]
        else:
            for q in range(a_in):
                acc = 0.0
                for c in range(a_out):
                    acc += W[l, m, q, c] * GA[l + 1, r, t, c]
                GA[l, r, t, q] = acc
        _times_derivative(code, Z, Y, GA, l, r, t, a_in)
    for e in range(n):
        gv[e] = 0.0
    for j in range(n):
        gj = G[r, t, j]
        for e in range(n):
            gv[e] += gj * A[r, j, e]
    w0 = dims[0]
    for q in range(reads.shape[0]):
        acc = 0.0
        for c in range(w0):
            acc += wu[m, q, c] * GA[0, r, t, c]
        gv[reads[q]] += acc


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def _sums(r, t, i, S, G, GA, OUT, index, g_d, g_pre, g_gain) -> None:  # noqa: ANN001, PLR0913  # pragma: no cover - compiled
    """Stage ``t``'s share of the drives' (half step ``i``), first layer's and gain's gradients."""
    m = r // S
    s = r - m * S
    for e in range(G.shape[2]):
        g_d[i, r, e] += G[r, t, e]
    for c in range(g_pre.shape[3]):
        g_pre[i, m, s, c] += GA[0, r, t, c]
    for c in range(index.shape[0]):
        g_gain[r, c] += G[r, t, index[c]] * OUT[r, t, c]


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _backward_row(r, h, grad, A, wu, W, dims, gain, reads, index, codes, S, boxed, Z, Y, OUT, MASK,  # noqa: ANN001, ANN202, PLR0913
                  g_u0, G, GA, g_d, g_pre, g_gain):  # pragma: no cover - compiled
    code = codes[r // S]
    n = g_u0.shape[1]
    steps = grad.shape[0] - 1
    lam = np.empty(n, grad.dtype)
    g23 = np.empty(n, grad.dtype)
    l4 = np.empty(n, grad.dtype)
    l3 = np.empty(n, grad.dtype)
    l2 = np.empty(n, grad.dtype)
    l1 = np.empty(n, grad.dtype)
    for e in range(n):
        lam[e] = 0.0
    for kk in range(steps - 1, -1, -1):
        t = 4 * kk
        for e in range(n):
            x = lam[e] + grad[kk + 1, r, e]
            if boxed:
                x = x * MASK[r, t + 3, e]
            lam[e] = x
            g23[e] = x * (h / 3.0)
            G[r, t + 3, e] = x * (h / 6.0)
        _vjp(r, t + 3, G, l4, A, wu, W, dims, gain, reads, index, code, S, Z, Y, GA)
        _sums(r, t + 3, 2 * kk + 2, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l4[e] = l4[e] * MASK[r, t + 2, e]
            G[r, t + 2, e] = g23[e] + h * l4[e]
        _vjp(r, t + 2, G, l3, A, wu, W, dims, gain, reads, index, code, S, Z, Y, GA)
        _sums(r, t + 2, 2 * kk + 1, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l3[e] = l3[e] * MASK[r, t + 1, e]
            G[r, t + 1, e] = g23[e] + (0.5 * h) * l3[e]
        _vjp(r, t + 1, G, l2, A, wu, W, dims, gain, reads, index, code, S, Z, Y, GA)
        _sums(r, t + 1, 2 * kk + 1, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l2[e] = l2[e] * MASK[r, t, e]
            G[r, t, e] = G[r, t + 3, e] + (0.5 * h) * l2[e]
        _vjp(r, t, G, l1, A, wu, W, dims, gain, reads, index, code, S, Z, Y, GA)
        _sums(r, t, 2 * kk, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            lam[e] = (((lam[e] + l4[e]) + l3[e]) + l2[e]) + l1[e]
    for e in range(n):
        g_u0[r, e] = lam[e] + grad[0, r, e]


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def backward(h, grad, A, wu, W, dims, gain, reads, index, codes, S, boxed, Z, Y, OUT, MASK,  # noqa: ANN001, ANN201, PLR0913
             g_u0, G, GA, g_d, g_pre, g_gain):  # pragma: no cover - compiled
    g_d[:] = 0.0
    g_pre[:] = 0.0
    g_gain[:] = 0.0
    for r in range(g_u0.shape[0]):
        _backward_row(r, h, grad, A, wu, W, dims, gain, reads, index, codes, S, boxed, Z, Y, OUT, MASK,
                      g_u0, G, GA, g_d, g_pre, g_gain)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", parallel=True)
def backward_threads(h, grad, A, wu, W, dims, gain, reads, index, codes, S, boxed, Z, Y, OUT, MASK,  # noqa: ANN001, ANN201, PLR0913
                     g_u0, G, GA, g_d, g_pre, g_gain):  # pragma: no cover - compiled
    """:func:`backward` with the rows shared among numba's threads (each row's sums are its own)."""
    g_d[:] = 0.0
    g_pre[:] = 0.0
    g_gain[:] = 0.0
    for r in numba.prange(g_u0.shape[0]):
        _backward_row(r, h, grad, A, wu, W, dims, gain, reads, index, codes, S, boxed, Z, Y, OUT, MASK,
                      g_u0, G, GA, g_d, g_pre, g_gain)
