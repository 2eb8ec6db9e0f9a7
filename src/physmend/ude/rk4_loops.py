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
evaluated ``Vs (R, T, n)``, for each activated layer the activation's derivative and value ``Z, Y
(L, R, T, P)`` (``Z`` holds the pre-activation until the activation overwrites it with the
derivative: the backward pass needs nothing else, and the forward pass has what it is made of),
the network's output ``OUT (R, T, k)`` and, per clamp, 1 where the state was inside the box
``MASK (R, T, n)`` (clamp ``4k+s`` holds stage ``s+2``'s state, the last one step ``k``'s end).

Backward, from ``grad (K+1, R, n)``, writes ``g_u0 (R, n)``, what each stage's right-hand side
received ``G (R, T, n)``, the gradient of every layer's pre-activation ``GA (L+1, R, T, P)`` (the
output layer's at ``L``), and the sums over stages that belong to one half step or one row:
``g_d (H, R, n)``, ``g_pre (H, M, S, w₀)``, ``g_gain (R, k)``. The weight and matrix gradients are
products over all stages of these, taken in :mod:`physmend.ude.compiled_solve`.

Activations are numbered as :data:`physmend.ude.activation_loops.CODES` (written without
the C library so that a layer's loop is vector instructions), one per model (``codes (M,)``, row
``r`` model ``r // S``'s:
:func:`physmend.ude.compiled_solve.codes`), so models with different activations are one solve.
NaN and infinity pass through as in torch (the fast math flags allow reassociation only).
"""

from __future__ import annotations

import numba
import numpy as np

from physmend.ude.activation_loops import FAST, activate

_FAST = FAST


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _rhs(r, t, i, Vs, du, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover
    """``du = f(Vs[r, t])`` for row ``r`` at stage ``t`` (half step ``i``), keeping the stage's layers;
    ``keep``: ``Z`` left holding the activations' derivatives (a training solve's forward pass).
    ``acc (P,)``: the row's scratch, where each layer's sums are taken before they are stored in
    ``Z`` (summed in place in ``Z``, each term is a load and a store of ``Z`` that the compiler
    cannot keep in registers, ``Z`` and ``W`` being arrays it cannot tell apart; the same sums in
    the same order)."""
    m = r // S
    s = r - m * S
    n = du.shape[0]
    L = W.shape[0]
    w0 = dims[0]
    for c in range(w0):
        acc[c] = pre[i, m, s, c]
    for q in range(reads.shape[0]):
        vq = Vs[r, t, reads[q]]
        for c in range(w0):
            acc[c] += vq * wu[m, q, c]
    for c in range(w0):
        Z[0, r, t, c] = acc[c]
    activate(code, Z, Y, L - L, r, t, w0, keep)  # layer 0 as a run-time integer: a literal 0 would compile each loop twice
    for l in range(L - 1):
        a_in, a_out = dims[l], dims[l + 1]
        for c in range(a_out):
            acc[c] = b[l, m, c]
        for q in range(a_in):
            yq = Y[l, r, t, q]
            for c in range(a_out):
                acc[c] += yq * W[l, m, q, c]
        for c in range(a_out):
            Z[l + 1, r, t, c] = acc[c]
        activate(code, Z, Y, l + 1, r, t, a_out, keep)
    a_in, k = dims[L - 1], dims[L]
    for c in range(k):
        dot = 0.0
        for q in range(a_in):
            dot += W[L - 1, m, c, q] * Y[L - 1, r, t, q]
        OUT[r, t, c] = b[L - 1, m, c] + dot
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
    acc = np.empty(Z.shape[3], Z.dtype)
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
        _rhs(r, t, 2 * kk, Vs, k1, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, True)
        _stage(r, t, t, 0.5 * h, k1, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 1, 2 * kk + 1, Vs, k2, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, True)
        _stage(r, t, t + 1, 0.5 * h, k2, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 2, 2 * kk + 1, Vs, k3, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, True)
        _stage(r, t, t + 2, h, k3, boxed, lo, hi, Vs, MASK)
        _rhs(r, t + 3, 2 * kk + 2, Vs, k4, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, True)
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
def _vjp(r, t, G, gv, A, wu, W, dims, gain, reads, index, S, Z, GA, acc):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover
    """``gv = J_f(Vs[r, t])ᵀ G[r, t]`` for row ``r`` at stage ``t``, keeping each layer's ``∂pre-activation``
    (``Z``: the activations' derivatives, as the forward pass left them; ``acc (P,)``: the row's
    scratch for the output layer's sums, as in :func:`_rhs`)."""
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
                acc[q] = 0.0
            for c in range(a_out):
                uc = GA[l + 1, r, t, c]
                for q in range(a_in):
                    acc[q] += uc * W[l, m, c, q]
            for q in range(a_in):
                GA[l, r, t, q] = acc[q] * Z[l, r, t, q]
        else:
            for q in range(a_in):
                dot = 0.0
                for c in range(a_out):
                    dot += W[l, m, q, c] * GA[l + 1, r, t, c]
                GA[l, r, t, q] = dot * Z[l, r, t, q]
    for e in range(n):
        gv[e] = 0.0
    for j in range(n):
        gj = G[r, t, j]
        for e in range(n):
            gv[e] += gj * A[r, j, e]
    w0 = dims[0]
    for q in range(reads.shape[0]):
        dot = 0.0
        for c in range(w0):
            dot += wu[m, q, c] * GA[0, r, t, c]
        gv[reads[q]] += dot


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
    n = g_u0.shape[1]
    steps = grad.shape[0] - 1
    lam = np.empty(n, grad.dtype)
    g23 = np.empty(n, grad.dtype)
    l4 = np.empty(n, grad.dtype)
    l3 = np.empty(n, grad.dtype)
    l2 = np.empty(n, grad.dtype)
    l1 = np.empty(n, grad.dtype)
    acc = np.empty(GA.shape[3], GA.dtype)
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
        _vjp(r, t + 3, G, l4, A, wu, W, dims, gain, reads, index, S, Z, GA, acc)
        _sums(r, t + 3, 2 * kk + 2, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l4[e] = l4[e] * MASK[r, t + 2, e]
            G[r, t + 2, e] = g23[e] + h * l4[e]
        _vjp(r, t + 2, G, l3, A, wu, W, dims, gain, reads, index, S, Z, GA, acc)
        _sums(r, t + 2, 2 * kk + 1, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l3[e] = l3[e] * MASK[r, t + 1, e]
            G[r, t + 1, e] = g23[e] + (0.5 * h) * l3[e]
        _vjp(r, t + 1, G, l2, A, wu, W, dims, gain, reads, index, S, Z, GA, acc)
        _sums(r, t + 1, 2 * kk + 1, S, G, GA, OUT, index, g_d, g_pre, g_gain)
        for e in range(n):
            if boxed:
                l2[e] = l2[e] * MASK[r, t, e]
            G[r, t, e] = G[r, t + 3, e] + (0.5 * h) * l2[e]
        _vjp(r, t, G, l1, A, wu, W, dims, gain, reads, index, S, Z, GA, acc)
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
