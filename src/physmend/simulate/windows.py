"""Long records solved in windows side by side: a whole trajectory in a few batched solves.

A whole-trajectory solve of a long record (tens of thousands of samples) is a sequence of tens
of thousands of small steps, and eager PyTorch pays per step, not per number: the same loop over
64 windows of the record at once costs about what one window alone does. Here the record's time
axis is cut into ``S`` windows of equal row counts; every window is solved from a guess of its
start state, all windows in one batched solve (each batch element is a window of an experiment,
on a local time axis shared by the windows). The end of each window is the next window's start
for the next solve (a Jacobi sweep: the first window is exact after one solve, and a model that
forgets its start state within a window — damping, heat loss, any dissipative model — is exact
everywhere after two). The solves stop when every window started, to the solver's own tolerance
(``atol + rtol |u|``), where the window before it ended: the windows then join into one
trajectory, with a jump at each seam no larger than one of the solver's local errors.

Where that does not happen within :data:`MAX_SOLVES` solves (a model that remembers its start:
undamped, unstable, chaotic), or any solve fails, :func:`solve_in_windows` returns None and the
caller solves the record in one sequence as before: the windows cost at most
``MAX_SOLVES / MIN_WINDOWS`` of that solve on top. Records whose sample times are not on a
regular grid (the windows' local times would not coincide) and short records are always solved
in one sequence.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from physmend.simulate.core import OWN_METHODS, odeint
from physmend.simulate.errors import SimulationError
from physmend.simulate.inputs import PiecewiseLinear

Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: fewest rows of the time axis per window: a window must be long enough for a model to forget
#: where it started
MIN_ROWS = 128
#: fewest windows: below this, what failed windows would cost (:data:`MAX_SOLVES` of ``1/S`` of
#: the sequential solve) is not worth what they save
MIN_WINDOWS = 16
#: most windows: per-step cost grows with the batch beyond this for small models
MAX_WINDOWS = 64
#: batched solves before giving up (the first starts from guesses)
MAX_SOLVES = 4
#: a second solve whose seams moved more than this share of the first solve's seam change shows a
#: model that does not forget its start within a window: give up early
MIN_CONTRACTION = 0.1


def _windows(t: torch.Tensor) -> list[int] | None:
    """Row indices where the windows start (and the last row): ``S + 1`` of them, or None."""
    rows = t.shape[0]
    S = min(MAX_WINDOWS, (rows - 1) // MIN_ROWS)
    if S < MIN_WINDOWS:
        return None
    return [s * (rows - 1) // S for s in range(S + 1)]


def _local_axis(t: torch.Tensor, knots: torch.Tensor, edges: list[int]
                ) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]] | None:
    """The local times shared by every window (s from the window's start), the local kinks, and each
    window's rows' positions on that axis; None where the windows' times do not coincide."""
    spacing = torch.diff(t)
    positive = spacing[spacing > 0]
    if not positive.numel():
        return None
    quantum = 1e-6 * float(positive.min())  # far below a sample step, far above rounding in t - start
    starts = t[edges[:-1]]
    local_rows = [torch.round((t[a : b + 1] - t[a]) / quantum) for a, b in zip(edges[:-1], edges[1:])]
    axis_q = torch.unique(torch.cat(local_rows))
    longest = max(int(r.numel()) for r in local_rows)
    if axis_q.numel() > longest + 2:  # the windows' sample times do not line up: irregular sampling
        return None
    kinks: list[torch.Tensor] = []
    inner = knots[(knots > t[0]) & (knots < t[-1])].to(t.dtype)
    for s, start in enumerate(starts):
        end = t[edges[s + 1]]
        mine = inner[(inner > start) & (inner < end)]
        kinks.append(torch.round((mine - start) / quantum))
    kinks_q = torch.unique(torch.cat(kinks)) if kinks else axis_q[:0]
    if kinks_q.numel() > 2 * longest + 2:  # input knots off the windows' common grid
        return None
    where = [torch.searchsorted(axis_q, r) for r in local_rows]
    return axis_q * quantum, kinks_q * quantum, where


def solve_in_windows(rhs: Rhs, inputs: PiecewiseLinear, u0: torch.Tensor, t: torch.Tensor, *, method: str,
                     rtol: float, atol: float, options: dict[str, Any] | None = None) -> torch.Tensor | None:
    """States ``(T, B, n)`` of ``du/dt = rhs(u, x(t))`` from ``u0 (B, n)`` at ``t (T,)`` (s), solved in
    windows side by side (module docstring); None where the record is not solved that way (too
    short, irregular, not one of physmend's own solvers, gradients on (call it under ``torch.no_grad``), or the windows did not
    join), and the caller solves it in one sequence.

    ``rhs(u (..., B, n), x (..., B, m))`` must broadcast over leading dimensions (as every
    right-hand side the solvers' finite-difference Jacobians call does)."""
    options = dict(options or {})
    if method not in OWN_METHODS or options.get("jacobian") is not None or torch.is_grad_enabled():
        return None
    edges = _windows(t)
    if edges is None:
        return None
    axis = _local_axis(t, inputs.knots, edges)
    if axis is None:
        return None
    local, kinks, where = axis
    S, (B, n) = len(edges) - 1, u0.shape
    starts = t[edges[:-1]]  # (S,)
    options.pop("clocks", None)
    options.pop("tstops", None)
    if kinks.numel():
        options["tstops"] = kinks

    def f(tt: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        lead = u.shape[:-2]
        x = inputs.at_each((starts + tt)[:, None].expand(S, B))  # (S, B, m)
        return rhs(u.reshape(*lead, S, B, n), x).reshape(*lead, S * B, n)

    last = torch.stack([w[-1] for w in where])  # (S,): each window's last row on the local axis
    z = u0.expand(S, B, n).clone()  # first guesses: every window starts where the record does
    before = None
    with torch.no_grad():
        for _ in range(MAX_SOLVES):
            try:
                traj = odeint(f, z.reshape(S * B, n), local, method=method, rtol=rtol, atol=atol,
                              options=options).reshape(-1, S, B, n)
            except SimulationError:
                return None
            ends = traj[last, torch.arange(S)]  # (S, B, n)
            seams = (ends[:-1] - z[1:]).abs() / (atol + rtol * ends[:-1].abs())
            change = float(seams.max()) if S > 1 else 0.0
            if not change == change:  # NaN
                return None
            if change <= 1.0:
                out = torch.empty(t.shape[0], B, n, dtype=u0.dtype, device=u0.device)
                for s, (a, b) in enumerate(zip(edges[:-1], edges[1:])):
                    out[a : b + 1] = traj[where[s], s]
                out[0] = u0
                return out
            if before is not None and change > MIN_CONTRACTION * before:
                return None  # the seams do not settle: this model remembers its start
            before = change
            z = torch.cat([u0[None], ends[:-1]])
    return None
