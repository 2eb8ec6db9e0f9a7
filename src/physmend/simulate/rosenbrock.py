"""Batched, differentiable Rosenbrock 2(3) solver for stiff ODEs (Shampine & Reichelt's ode23s).

L-stable and linearly implicit: each step solves three linear systems with
``W = I - h d J`` (``J`` the batched Jacobian by finite differences in one broadcast call), so stiff thermal models
take steps sized by accuracy, not by their fastest time constant. All batch elements share one
step size. Dense output uses the method's own continuous extension.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from physmend.simulate.errors import SimulationError

Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

_D = 1.0 / (2.0 + math.sqrt(2.0))
_E32 = 6.0 + math.sqrt(2.0)


def batched_jacobian(f: Rhs, t: torch.Tensor, u: torch.Tensor, f_u: torch.Tensor | None = None) -> torch.Tensor:
    """``J[b, i, j] = d f_i / d u_j`` for ``u (B, n)``: ``(B, n, n)``.

    Forward differences with all ``n`` perturbed copies evaluated in *one* call: ``f`` must
    broadcast over a leading dimension (``(n, B, n) -> (n, B, n)``), as compiled models do. One
    batched call is far cheaper than ``n`` calls or forward-mode transforms on small models.
    """
    n = u.shape[-1]
    if f_u is None:
        f_u = f(t, u)
    step = math.sqrt(torch.finfo(u.dtype).eps) * u.detach().abs().clamp_min(1.0)  # (B, n)
    eye = torch.eye(n, dtype=u.dtype, device=u.device)
    perturbed = u[None] + eye[:, None, :] * step[None]  # (n, B, n): copy j has u_j moved
    df = (f(t, perturbed) - f_u[None]) / step.T[:, :, None]  # (n, B, n): [j, b, i]
    return df.permute(1, 2, 0)


def odeint_rosenbrock(
    f: Rhs,
    u0: torch.Tensor,
    t: torch.Tensor,
    *,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    first_step: float | None = None,
    max_steps: int = 100_000,
    names: list[str] | None = None,
    tstops: torch.Tensor | None = None,
    jacobian: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """Integrate ``du/dt = f(t, u)`` from ``u0 (B, n)`` and return ``u`` at times ``t (T,)``: ``(T, B, n)``.

    ``t`` must be increasing; ``t[0]`` is the initial time. ``tstops`` are times (s) where the
    right-hand side has kinks (knots of piecewise-linear inputs): steps end on them instead of
    straddling them, which avoids rejected steps. ``jacobian(t, u)`` gives ``df/du (B, n, n)``
    exactly (e.g. analytically); without it, forward differences (:func:`batched_jacobian`). Raises :class:`SimulationError`
    naming the experiment (``names[b]``) and the time when integration fails.
    """
    check_times(t)
    names = names or [str(i) for i in range(u0.shape[0])]
    out = [u0]
    t0, t_final = float(t[0]), float(t[-1])
    if t.numel() == 1:
        return u0[None]
    span = t_final - t0
    eye = torch.eye(u0.shape[-1], dtype=u0.dtype, device=u0.device)
    u = u0
    tc = t0
    f0 = f(t[0], u)
    _check_finite(f0, tc, names, "derivative")
    if first_step is None:
        scale = atol + rtol * u.abs()
        d0 = float((u / scale).pow(2).mean().sqrt())
        d1 = float((f0 / scale).pow(2).mean().sqrt())
        first_step = 0.01 * d0 / d1 if d0 > 1e-5 and d1 > 1e-5 else 1e-6 * max(span, 1.0)
        first_step = min(span, first_step)
    h_min = 1e-14 * max(span, 1.0)
    h = max(first_step, 10 * h_min)
    next_eval = 1
    steps = 0
    stops = [] if tstops is None else sorted(float(x) for x in tstops.detach().flatten() if t0 < float(x) < t_final)
    next_stop = 0
    h_wanted = h
    while next_eval < t.numel():
        steps += 1
        if steps > max_steps:
            raise SimulationError(
                f"integration stopped after max_steps={max_steps} at t = {tc:.6g} s "
                f"(experiments {names}); the model may be unstable or the tolerances too tight"
            )
        h = min(h, t_final - tc)
        while next_stop < len(stops) and stops[next_stop] <= tc + 1e-9 * max(abs(tc), 1.0):
            next_stop += 1
        h_wanted = h
        if next_stop < len(stops) and tc + h > stops[next_stop]:
            h = stops[next_stop] - tc
        tt = torch.as_tensor(tc, dtype=u.dtype, device=u.device)
        J = jacobian(tt, u) if jacobian is not None else batched_jacobian(f, tt, u, f0)
        delta = math.sqrt(torch.finfo(u.dtype).eps) * max(abs(tc), h)
        T = (f(tt + delta, u) - f0) / delta
        W = eye - (h * _D) * J
        lu, piv = torch.linalg.lu_factor(W)

        def solve(rhs: torch.Tensor) -> torch.Tensor:
            return torch.linalg.lu_solve(lu, piv, rhs[..., None])[..., 0]

        k1 = solve(f0 + (h * _D) * T)
        f1 = f(tt + 0.5 * h, u + 0.5 * h * k1)
        k2 = solve(f1 - k1) + k1
        u_new = u + h * k2
        f2 = f(tt + h, u_new)
        k3 = solve(f2 - _E32 * (k2 - f1) - 2.0 * (k1 - f0) + (h * _D) * T)
        err = (h / 6.0) * (k1 - 2.0 * k2 + k3)
        scale = atol + rtol * torch.maximum(u.abs(), u_new.abs())
        ratio = (err / scale).detach()
        per_elem = ratio.pow(2).mean(-1).sqrt()
        if not bool(torch.isfinite(per_elem).all()):
            bad = [names[i] for i in torch.nonzero(~torch.isfinite(per_elem)).flatten().tolist()]
            h *= 0.25
            if h < h_min:
                raise SimulationError(
                    f"integration failed for experiment(s) {bad} at t = {tc:.6g} s: the state or its "
                    "derivative became non-finite (NaN/inf)"
                )
            continue
        err_norm = float(per_elem.max())
        if err_norm <= 1.0:
            t_new = tc + h
            while next_eval < t.numel() and float(t[next_eval]) <= t_new + 1e-12 * max(abs(t_new), 1.0):
                s = (t[next_eval] - tc) / h
                c1 = s * (1 - s) / (1 - 2 * _D)
                c2 = s * (s - 2 * _D) / (1 - 2 * _D)
                out.append(u + h * (c1 * k1 + c2 * k2))
                next_eval += 1
            u, tc, f0 = u_new, t_new, f2
            if next_stop < len(stops) and abs(tc - stops[next_stop]) <= 1e-9 * max(abs(tc), 1.0):
                tc = stops[next_stop]  # landed on a kink: go on with the step size wanted before it
                h = max(h, h_wanted)
        worst = int(per_elem.argmax())
        factor = 0.9 * err_norm ** (-1.0 / 3.0) if err_norm > 0 else 5.0
        h = h * min(5.0, max(0.2, factor))
        if h < h_min:
            raise SimulationError(
                f"integration failed for experiment {names[worst]!r} at t = {tc:.6g} s: step size "
                f"underflow ({h:.3g} s); the model is unstable or discontinuous there"
            )
    return torch.stack(out)


def check_times(t: torch.Tensor) -> None:
    """Evaluation times must be a non-empty, non-decreasing 1-D tensor (s); SimulationError otherwise."""
    if t.ndim != 1 or t.numel() < 1:
        raise SimulationError(f"evaluation times must be a 1-D tensor, but got shape {tuple(t.shape)}")
    if t.numel() > 1 and not bool((t[1:] >= t[:-1]).all()):
        i = int(torch.nonzero(t[1:] < t[:-1]).flatten()[0])
        raise SimulationError(f"evaluation times must be non-decreasing, but t[{i + 1}] = {float(t[i + 1]):g} s "
                              f"follows t[{i}] = {float(t[i]):g} s")


def _check_finite(v: torch.Tensor, tc: float, names: list[str], what: str) -> None:
    ok = torch.isfinite(v).all(-1)
    if not bool(ok.all()):
        bad = [names[i] for i in torch.nonzero(~ok).flatten().tolist()]
        raise SimulationError(f"experiment(s) {bad}: non-finite {what} at t = {tc:.6g} s")
