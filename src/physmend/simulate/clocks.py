"""A clock per batch element: Rodas steps that end on each experiment's own times only.

A batch of experiments on one shared time axis (:class:`~physmend.simulate.batch.Batch`) is the
union of their sample times. With one step size for the whole batch, every step ends on the
union of every experiment's sample times and input knots: four experiments with jittered
timestamps make four times the steps each one needs. Here each element keeps its own time and
step size, its steps end on its own stops (its measured rows and the kinks of its own inputs),
and its values at the other experiments' times come from the method's continuous extension
within the step that spans them (rows that hold no measurement of that experiment). The
iterations of the batched loop are then as many as the busiest element needs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from physmend.simulate.errors import SimulationError
from physmend.simulate.rodas import _Coefficients, _value_and_jacobian, rodas_step, without_steps
from physmend.simulate.rosenbrock import check_times
from physmend.simulate.tableaus import tableau_named

Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _growth_rates(u: torch.Tensor, u_new: torch.Tensor, J: torch.Tensor, atol: float) -> torch.Tensor:
    """Largest real part of ``J``'s eigenvalues (1/s) for every element whose step changed its state
    by more than half its size, 0 elsewhere: ``(B,)`` (see :func:`~physmend.simulate.rodas._fast_growth`)."""
    change = (u_new - u).detach().norm(dim=-1)
    size = u.detach().norm(dim=-1) + atol * u.shape[-1] ** 0.5
    suspect = torch.nonzero(change > 0.5 * size).flatten()
    rates = torch.zeros(u.shape[0], dtype=u.dtype)
    if suspect.numel():
        rates[suspect] = torch.linalg.eigvals(J.detach()[suspect]).real.amax(-1).to(u.dtype)
    return rates


def odeint_rodas_each(
    f: Rhs,
    u0: torch.Tensor,
    t: torch.Tensor,
    stops: Sequence[torch.Tensor],
    *,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    first_step: float | None = None,
    max_steps: int = 100_000,
    names: list[str] | None = None,
    jacobian: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    tableau: str = "rodas4",
) -> torch.Tensor:
    """Integrate ``du/dt = f(t, u)`` from ``u0 (B, n)``, every element on its own clock; ``u`` at
    ``t (T,)``: ``(T, B, n)``.

    As :func:`~physmend.simulate.rodas.odeint_rodas`, except: ``f(t, u)`` and ``jacobian(t, u)``
    get ``t (B,)``, each element's own time (s); element ``b``'s steps end on ``stops[b]`` (its
    measured times and input kinks, s) and at ``t[-1]``, with its own step size and error
    control, and its values at the other times of ``t`` are the continuous extension of the step
    that spans them. ``max_steps`` counts iterations (each attempts a step of every unfinished
    element).
    """
    check_times(t)
    B = u0.shape[0]
    names = names or [str(i) for i in range(B)]
    if len(stops) != B:
        raise SimulationError(f"a clock per batch element needs {B} lists of stops, but got {len(stops)}")
    t0, t_final = float(t[0]), float(t[-1])
    if (done_now := without_steps(t, u0)) is not None:
        return done_now
    tab = tableau_named(tableau)
    co = _Coefficients(tab, u0)
    dtype = u0.dtype
    span = t_final - t0
    h_min = 1e-14 * max(span, 1.0)
    near = 1e-9 * max(abs(t0), abs(t_final), 1.0)
    own = [sorted({x for x in s.detach().flatten().tolist() if t0 < x < t_final - near}) + [t_final] for s in stops]
    nxt = np.zeros(B, dtype=np.int64)  # index of each element's next stop
    stop_at = np.array([o[0] for o in own])
    tc = np.full(B, t0)
    h = np.full(B, np.nan if first_step is None else max(first_step, 10 * h_min))
    rejected = np.zeros(B, dtype=bool)
    done = np.zeros(B, dtype=bool)
    u = u0
    starts: list[np.ndarray] = []  # per iteration: each element's step start, end (NaN: not accepted)
    ends: list[np.ndarray] = []
    steps_u: list[torch.Tensor] = []
    steps_new: list[torch.Tensor] = []
    steps_k: list[torch.Tensor] = []
    iterations = 0
    while not done.all():
        iterations += 1
        if iterations > max_steps:
            late = [names[b] for b in np.nonzero(~done)[0]]
            raise SimulationError(
                f"integration stopped after max_steps={max_steps} at t = {float(tc[~done].min()):.6g} s "
                f"(experiments {late}); the model may be unstable or the tolerances too tight")
        tt = torch.as_tensor(tc, dtype=dtype)
        if jacobian is not None:
            f0 = f(tt, u)
            J = jacobian(tt, u)
        else:
            f0, J = _value_and_jacobian(f, tt, u)
        bad = ~torch.isfinite(f0).all(-1).cpu().numpy() & ~done
        if bad.any():
            b = int(np.nonzero(bad)[0][0])
            raise SimulationError(f"experiment(s) {[names[i] for i in np.nonzero(bad)[0]]}: non-finite derivative "
                                  f"at t = {tc[b]:.6g} s")
        fresh = np.isnan(h)
        if fresh.any():  # first step size from the state's and derivative's scale (Hairer's heuristic)
            scale = atol + rtol * u.detach().abs()
            d0 = (u.detach() / scale).pow(2).mean(-1).sqrt().cpu().numpy()
            d1 = (f0.detach() / scale).pow(2).mean(-1).sqrt().cpu().numpy()
            guess = np.where((d0 > 1e-5) & (d1 > 1e-5), 0.01 * d0 / np.maximum(d1, 1e-300), 1e-6 * max(span, 1.0))
            h = np.where(fresh, np.maximum(np.minimum(span, guess), 10 * h_min), h)
        delta = math.sqrt(torch.finfo(dtype).eps) * np.maximum(np.abs(tc), h)
        dt_ = torch.as_tensor(delta, dtype=dtype)
        dfdt = (f(tt + dt_, u) - f0) / dt_[:, None]  # forward difference: the input segment after tc
        h = np.minimum(h, t_final - tc)
        h_wanted = h.copy()
        h = np.where(tc + h > stop_at, stop_at - tc, h)
        h_try = np.where(done, 10 * h_min, np.maximum(h, h_min))  # finished elements: a tiny step, discarded
        step = rodas_step(f, tt, u, torch.as_tensor(h_try, dtype=dtype), f0, J, dfdt, tab, co)
        scale = atol + rtol * torch.maximum(u.abs(), step.u_new.abs())
        err = (step.err / scale).detach().pow(2).mean(-1).sqrt().cpu().numpy().copy()
        err[done] = 0.0
        finite = np.isfinite(err)
        safe = np.where(finite, err, 1.0)
        exponent = np.where(safe <= 1.0, 1.0 / tab.order, max(1.0 / tab.order, 1.0 / 3.0))
        factor = np.where(safe > 0, np.clip(0.9 * np.maximum(safe, 1e-300) ** -exponent, 0.2, 6.0), 6.0)
        ok = finite & (err <= 1.0) & ~done
        fast = np.zeros(B, dtype=bool)
        if ok.any():
            rates = _growth_rates(u, step.u_new, J, atol).cpu().numpy()
            fast = ok & (h * rates > 1.0)  # a mode grows faster than the step can follow: retry shorter
            h = np.where(fast, np.minimum(h * factor, 0.5 / np.maximum(rates, 1e-300)), h)
            ok &= ~fast
        retry = ~ok & ~done
        h = np.where(retry, np.where(finite, h * factor, h * 0.25), h)
        rejected |= retry
        if ok.any():
            acc = torch.as_tensor(ok)
            t_new = tc + h
            landed = ok & (np.abs(t_new - stop_at) <= near)
            t_new = np.where(landed, stop_at, t_new)
            starts.append(np.where(ok, tc, np.nan))
            ends.append(np.where(ok, t_new, np.nan))
            steps_u.append(u)
            steps_new.append(step.u_new)
            steps_k.append(step.ks)
            u = torch.where(acc[:, None], step.u_new, u)
            grow = np.where(rejected, np.minimum(factor, 1.0), factor)  # no growth right after a rejection
            h_next = h * grow
            h_next = np.where(landed & (grow >= 1.0), np.maximum(h_next, h_wanted), h_next)
            tc = np.where(ok, t_new, tc)
            h = np.where(ok, h_next, h)
            rejected &= ~ok
            for b in np.nonzero(landed)[0]:
                nxt[b] += 1
                done[b] = nxt[b] >= len(own[b])
                if not done[b]:
                    stop_at[b] = own[b][nxt[b]]
        small = ~done & (h < h_min)
        if small.any():
            b = int(np.nonzero(small)[0][0])
            what = "the state or its derivative became non-finite (NaN/inf)" if not finite[b] else \
                f"step size underflow ({h[b]:.3g} s); the model is unstable or discontinuous there"
            raise SimulationError(f"integration failed for experiment {names[b]!r} at t = {tc[b]:.6g} s: {what}")
    return _on_times(t, u0, np.stack(starts), np.stack(ends), torch.stack(steps_u), torch.stack(steps_new),
                     torch.stack(steps_k), co.H)


def _on_times(t: torch.Tensor, u0: torch.Tensor, starts: np.ndarray, ends: np.ndarray, us: torch.Tensor,
              news: torch.Tensor, ks: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
    """Every element's state at every time of ``t (T,)`` from its accepted steps: ``(T, B, n)``.

    ``starts``, ``ends (I, B)``: each iteration's step of each element (NaN where not accepted);
    ``us``, ``news (I, B, n)``: states at their starts and ends; ``ks (I, s, B, n)`` the stage
    increments. A time at a step's end is that end; one inside a step its continuous extension.
    """
    times = t.detach().cpu().numpy()
    B = u0.shape[0]
    cols = []
    for b in range(B):
        rows = np.nonzero(~np.isnan(ends[:, b]))[0]
        e = ends[rows, b]
        s0 = starts[rows, b]
        j = np.clip(np.searchsorted(e, times[1:], side="left"), 0, len(rows) - 1)  # the step ending at or after
        frac = np.clip((times[1:] - s0[j]) / np.maximum(e[j] - s0[j], 1e-300), 0.0, 1.0)
        idx = torch.as_tensor(rows[j])
        a = us[idx, b]  # (T-1, n)
        z = news[idx, b]
        sv = torch.as_tensor(frac, dtype=u0.dtype)[:, None]
        if H.numel():
            m = H.shape[1]
            k = torch.einsum("cm,tmn->ctn", H, ks[idx, :m, b])  # (2, T-1, n)
            val = (1 - sv) * a + sv * (z + (1 - sv) * (k[0] + sv * k[1]))
        else:
            val = (1 - sv) * a + sv * z
        cols.append(torch.cat([u0[b][None], val]))
    return torch.stack(cols, dim=1)
