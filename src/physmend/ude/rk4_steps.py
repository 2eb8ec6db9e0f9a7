"""A whole-trajectory RK4 solve of the drive form, compiled (numba): each row on its own steps.

The same right-hand side as the training solve (:mod:`physmend.ude.rk4_loops`, whose layout and
``_rhs`` this uses), but for simulations that need no gradient: nothing is kept per stage (the
stages live in a scratch of four), each row ``r`` takes the steps ``hs[r, :]`` (s; a step of 0
leaves the state as it is, for rows with fewer steps than others), and besides the grid points the
loop writes the derivative there, for a cubic Hermite interpolant between them.

Layout as :mod:`physmend.ude.rk4_loops` except: ``hs (R, K)``; ``d (H, R, n)`` and
``pre (H, M, S, w₀)`` at each row's own half steps (``H = 2K+1``: step ``k`` evaluates half steps
``2k``, ``2k+1``, ``2k+2``); scratch ``Vs (R, 4, n)``, ``Z, Y (L, R, 4, P)``, ``OUT (R, 4, k)``.
Writes ``traj (K+1, R, n)`` and ``slope (K+1, R, n)``.
"""

from __future__ import annotations

import numba
import numpy as np

from physmend.ude.rk4_loops import _FAST, _rhs


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def _row(r, hs, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S,  # noqa: ANN001, ANN202, PLR0913
         traj, slope, Vs, Z, Y, OUT):  # pragma: no cover - compiled
    code = codes[r // S]
    n = u0.shape[1]
    steps = hs.shape[1]
    acc = np.empty(Z.shape[3], Z.dtype)
    k1 = np.empty(n, u0.dtype)
    k2 = np.empty(n, u0.dtype)
    k3 = np.empty(n, u0.dtype)
    k4 = np.empty(n, u0.dtype)
    for e in range(n):
        traj[0, r, e] = u0[r, e]
    for kk in range(steps + 1):
        # the stage slots as plain integers: literal ones would compile _rhs a second time
        s0 = kk - kk
        s1, s2, s3 = s0 + 1, s0 + 2, s0 + 3
        for e in range(n):
            Vs[r, 0, e] = traj[kk, r, e]
        _rhs(r, s0, 2 * kk, Vs, k1, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, False)
        for e in range(n):
            slope[kk, r, e] = k1[e]
        if kk == steps:
            break
        h = hs[r, kk]
        for e in range(n):
            Vs[r, 1, e] = Vs[r, 0, e] + 0.5 * h * k1[e]
        _rhs(r, s1, 2 * kk + 1, Vs, k2, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, False)
        for e in range(n):
            Vs[r, 2, e] = Vs[r, 0, e] + 0.5 * h * k2[e]
        _rhs(r, s2, 2 * kk + 1, Vs, k3, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, False)
        for e in range(n):
            Vs[r, 3, e] = Vs[r, 0, e] + h * k3[e]
        _rhs(r, s3, 2 * kk + 2, Vs, k4, At, d, pre, wu, W, b, dims, gain, reads, index, code, S, Z, Y, OUT, acc, False)
        h6 = h / 6.0
        for e in range(n):
            traj[kk + 1, r, e] = Vs[r, 0, e] + h6 * ((k1[e] + 2.0 * (k2[e] + k3[e])) + k4[e])


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy")
def steps(hs, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S,  # noqa: ANN001, ANN201, PLR0913
          traj, slope, Vs, Z, Y, OUT):  # pragma: no cover - compiled
    """Every row's steps, one row after another (module docstring)."""
    for r in range(u0.shape[0]):
        _row(r, hs, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, traj, slope, Vs, Z, Y, OUT)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", parallel=True)
def steps_threads(hs, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S,  # noqa: ANN001, ANN201, PLR0913
                  traj, slope, Vs, Z, Y, OUT):  # pragma: no cover - compiled
    """:func:`steps` with the rows shared among numba's threads."""
    for r in numba.prange(u0.shape[0]):
        _row(r, hs, u0, At, d, pre, wu, W, b, dims, gain, reads, index, codes, S, traj, slope, Vs, Z, Y, OUT)
