"""Exact whole-trajectory solution of an affine model driven by piecewise-linear inputs.

Where every row of ``du/dt`` is affine in states and inputs, ``du/dt = A u + B x(t) + c`` with
``A, B, c`` fixed per experiment (:class:`physmend.modeling.compile.BoundRhs`), and the inputs
are linear between consecutive knots, the state at the end of each interval of length ``h``
follows from the state at its start by one matrix exponential (first-order hold): with
``tau = (t - t_k) / h`` and ``x = x_k + tau d_k``, the augmented state ``z = [u, x, 1, d]``
obeys ``dz/dtau = Z z``,

    Z = [[h A, h B, h c, 0],
         [0,   0,   0,   I],
         [0,   0,   0,   0],
         [0,   0,   0,   0]],

so ``u_{k+1} = E_uu u_k + E_ux x_k + E_u1 + E_ud d_k`` with ``E = exp(Z)`` (Van Loan's block
exponential). This is what every solver approximates; here it costs one matrix exponential per
distinct interval length and one small matrix product per interval, instead of a Rosenbrock step
(a Jacobian, a factorisation and six right-hand sides) per interval or less. Long records of
linear models (thermal networks, mass-spring-dampers) are simulated in a fraction of a second.

Only for evaluations that need no gradient (:func:`exact_affine` returns None otherwise, and
where the solution leaves float range: a model that blows up is left to the solvers, which say
where).
"""

from __future__ import annotations

import torch

from physmend.modeling.compile import BoundRhs
from physmend.simulate.inputs import PiecewiseLinear

#: interval lengths that differ by less than this share of the longest are one length (sample
#: times read from a file differ from a uniform grid in their last bits); the error this makes is
#: ``|A| · δh · |u|`` per interval, far below any solver tolerance
SAME_LENGTH = 1e-10
#: intervals whose matrix exponentials are built at once: bounds memory to about
#: ``CHUNK · B · (n + 2m + 1)²`` numbers
CHUNK = 4096


def _grid(t: torch.Tensor, knots: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The union of the evaluation times ``t (T,)`` and the knots inside them (s): ``(G,)``, and
    where each evaluation time sits in it: ``(T,)``."""
    inner = knots[(knots > t[0]) & (knots < t[-1])].to(t.dtype)
    grid = torch.unique(torch.cat([t, inner]))
    return grid, torch.searchsorted(grid, t)


def _exponentials(bound: BoundRhs, h: torch.Tensor) -> torch.Tensor:
    """``exp(Z)`` for each interval length ``h (U,)`` and batch element: ``(U, B, n, N)``, the rows
    of the states only (``N = n + 2m + 1`` columns: states, inputs, constant, input change)."""
    A, c = bound.A, bound.c  # (B, n, n), (B, n)
    Bm = bound.B  # (B, n, m)
    b, n = A.shape[0], A.shape[-1]
    m = Bm.shape[-1]
    N = n + 2 * m + 1
    Z = A.new_zeros(h.shape[0], b, N, N)
    hh = h[:, None, None, None]
    Z[..., :n, :n] = hh * A[None]
    if m:
        Z[..., :n, n : n + m] = hh * Bm[None]
        Z[..., n : n + m, n + m + 1 :] = torch.eye(m, dtype=A.dtype, device=A.device)
    Z[..., :n, n + m] = h[:, None, None] * c[None]
    return torch.linalg.matrix_exp(Z)[..., :n, :]


def exact_affine(bound: BoundRhs, inputs: PiecewiseLinear, u0: torch.Tensor, t: torch.Tensor) -> torch.Tensor | None:
    """States of the affine system ``bound`` from ``u0 (B, n)`` at times ``t (T,)`` (s): ``(T, B, n)``.

    None where the model is not affine in every row, where a gradient is wanted, or where the
    solution is not finite (a model that blows up: the solvers report where it does)."""
    if bound.split.rest is not None or (torch.is_grad_enabled() and (bound.A.requires_grad or bound.c.requires_grad
                                                                      or bound.B.requires_grad or u0.requires_grad)):
        return None
    if t.numel() < 2 or float(t[-1]) == float(t[0]):
        return torch.stack([u0] * t.numel())
    with torch.no_grad():
        grid, rows = _grid(t, inputs.knots)
        x = inputs.at(grid)  # (G, B, m): linear between consecutive grid points
        h_all = grid[1:] - grid[:-1]  # (G - 1,)
        quantum = SAME_LENGTH * float(h_all.max())
        states = [u0]
        u = u0.unsqueeze(-1)  # (B, n, 1)
        n, m = u0.shape[-1], x.shape[-1]
        for start in range(0, h_all.shape[0], CHUNK):
            h = h_all[start : start + CHUNK]
            lengths, which = torch.unique(torch.round(h / quantum), return_inverse=True)
            E = _exponentials(bound, lengths * quantum)  # (U, B, n, N)
            xs, dx = x[start : start + h.shape[0]], x[start + 1 : start + 1 + h.shape[0]] - x[start : start + h.shape[0]]
            Ek = E[which]  # (C, B, n, N)
            # what the inputs and the constant add over each interval: (C, B, n, 1)
            drive = Ek[..., n + m : n + m + 1]
            if m:
                drive = drive + Ek[..., n : n + m] @ xs.unsqueeze(-1) + Ek[..., n + m + 1 :] @ dx.unsqueeze(-1)
            phi = Ek[..., :n].contiguous()
            for k in range(h.shape[0]):
                u = torch.baddbmm(drive[k], phi[k], u)
                states.append(u.squeeze(-1))
        out = torch.stack(states)[rows]
    return out if bool(torch.isfinite(out).all()) else None
