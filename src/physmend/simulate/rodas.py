"""Batched, differentiable Rodas solvers for stiff ODEs: stiffly accurate, L-stable Rosenbrock methods.

Each step needs one Jacobian (the given ``jacobian``, or forward differences in the same
broadcast call that gives the step's first right-hand side), one LU factorisation of
``W = I/(gamma h) - J`` and one triangular solve per stage, all batched over the batch
elements, which share one step size (:mod:`physmend.simulate.clocks`: each its own). The last stage's ``k`` is the difference to an embedded
solution one order lower: the error estimate.

The tableaus (Rodas3, Rodas4, Rodas4P, Rodas4P2) are in :mod:`physmend.simulate.tableaus`.

All are written in the transformed variables of those codes: stage ``i`` solves

    (I/(gamma h) - J) k_i = f(t + c_i h, u + sum_j a_ij k_j) + sum_j (C_ij / h) k_j + h d_i df/dt,

and the last stage's argument plus its ``k`` is the new solution. ``df/dt`` is a forward
difference (inputs are piecewise linear in time). Steps end on the evaluation times and on
``tstops``, so every returned value is an error-controlled step end: the order-3 continuous
extension (``RodasStep.dense``) is far less accurate on stiff problems driven by inputs, where
the step-end error estimate lets steps grow long.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from physmend.simulate.errors import SimulationError
from physmend.simulate.rosenbrock import _check_finite, check_times
from physmend.simulate.tableaus import RODAS4, RodasTableau, tableau_named

Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass
class RodasStep:
    """One Rodas step from ``u (B, n)`` over ``h`` (s): new state, error estimate, dense output.

    ``u_new``, ``err``: ``(B, n)`` (``err`` is the difference to the embedded order-3 solution,
    in state units); ``ks``: the stage increments stacked, ``(s, B, n)``.
    """

    u: torch.Tensor
    u_new: torch.Tensor
    err: torch.Tensor
    ks: torch.Tensor
    H: torch.Tensor  # (2, 5): the tableau's dense-output rows
    _k: torch.Tensor | None = None  # (2, B, n): H @ ks, once the first dense value is asked for

    def dense(self, s: float) -> torch.Tensor:
        """State at the fraction ``s`` in [0, 1] of the step: ``(B, n)`` (third order)."""
        if self.H.numel() == 0:  # no continuous extension: linear
            return (1 - s) * self.u + s * self.u_new
        if self._k is None:
            m = self.H.shape[1]
            self._k = torch.mm(self.H, self.ks[:m].reshape(m, -1)).reshape(2, *self.u.shape)
        k = self._k
        return (1 - s) * self.u + s * (self.u_new + (1 - s) * (k[0] + s * k[1]))


class _Coefficients:
    """A tableau's coefficients as tensors of one dtype and device (built once per solve).

    ``AC[i]``: ``(2, s - 1)``, stage ``i``'s ``a`` (row 0) and ``C`` (row 1) on earlier stages,
    zero-padded; ``H``: ``(2, m)`` (``(1, 0)`` without dense output); ``same_as[i]``: the first
    stage evaluated at stage ``i``'s point.
    """

    def __init__(self, tab: RodasTableau, like: torch.Tensor) -> None:
        stages = len(tab.c)
        ac = torch.zeros(stages, 2, stages - 1, dtype=torch.float64)
        for i in range(1, stages):
            ac[i, 0, :i] = torch.tensor(tab.a[i], dtype=torch.float64)
            ac[i, 1, :i] = torch.tensor(tab.C[i], dtype=torch.float64)
        self.tab = tab
        self.AC = ac.to(dtype=like.dtype, device=like.device)
        self.H = torch.tensor(tab.H or ((),), dtype=like.dtype, device=like.device)  # (2, m) or (1, 0)
        # a stage at the point of an earlier one (same time, same a row) reuses its f
        points = [(tab.c[i], tuple(tab.a[i]) + (0.0,) * (stages - 1 - len(tab.a[i]))) for i in range(stages)]
        self.same_as = [points.index(points[i]) for i in range(stages)]
        self.eye = torch.eye(like.shape[-1], dtype=like.dtype, device=like.device)


def rodas_step(
    f: Rhs,
    t: torch.Tensor,
    u: torch.Tensor,
    h: float | torch.Tensor,
    f0: torch.Tensor,
    J: torch.Tensor,
    dfdt: torch.Tensor,
    tableau: RodasTableau = RODAS4,
    coefficients: _Coefficients | None = None,
) -> RodasStep:
    """Advance ``u (B, n)`` at time ``t`` (s, scalar tensor) by one step of ``h`` seconds.

    ``f0 = f(t, u)`` and ``dfdt`` (``(B, n)``, per second) and the Jacobian ``J = df/du (B, n, n)``
    are evaluated at ``(t, u)`` by the caller (they are reused when a step is retried). One LU
    factorisation of ``I/(gamma h) - J`` and a right-hand side per stage at a new point follow
    (five for the Rodas4 family, two for Rodas3). With a clock per element (``t`` and ``h`` both
    ``(B,)``, :func:`physmend.simulate.clocks.odeint_rodas_each`) each element takes its own step.
    """
    co = coefficients if coefficients is not None and coefficients.tab is tableau else _Coefficients(tableau, u)
    tab = tableau
    hv = h[:, None] if isinstance(h, torch.Tensor) else h  # multiplies (B, n)
    lu, piv = torch.linalg.lu_factor(co.eye / (tab.gamma * (h[:, None, None] if isinstance(h, torch.Tensor) else h)) - J)
    flat = u.numel()

    def solve(rhs: torch.Tensor) -> torch.Tensor:
        return torch.linalg.lu_solve(lu, piv, rhs[..., None])[..., 0]

    ks = [solve(f0 + (hv * tab.d[0]) * dfdt)]
    points = [u]  # each stage's argument
    values = [f0]  # f there
    for i in range(1, len(tab.c)):
        # a- and C-weighted sums of the earlier stages in one product: (2, i) @ (i, B n)
        mix = torch.mm(co.AC[i, :, :i], torch.stack(ks).reshape(i, flat)).reshape(2, *u.shape)
        j = co.same_as[i]
        if j < i:
            points.append(points[j])
            values.append(values[j])
        else:
            points.append(u + mix[0])
            values.append(f(t + tab.c[i] * h, points[i]))
        rhs = values[i] + mix[1] / hv
        if tab.d[i] != 0.0:
            rhs = rhs + (hv * tab.d[i]) * dfdt
        ks.append(solve(rhs))
    return RodasStep(u=u, u_new=points[-1] + ks[-1], err=ks[-1], ks=torch.stack(ks), H=co.H)


def _value_and_jacobian(f: Rhs, t: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``f(t, u) (B, n)`` and its forward-difference Jacobian ``(B, n, n)`` from one broadcast call.

    As :func:`~physmend.simulate.rosenbrock.batched_jacobian`, with the unperturbed ``u`` as an
    extra copy (``f`` gets ``u (n + 1, B, n)``), so the step's first right-hand side costs no
    call of its own (Rodas, unlike ode23s, does not evaluate ``f`` at the new step end).
    """
    n = u.shape[-1]
    step = math.sqrt(torch.finfo(u.dtype).eps) * u.detach().abs().clamp_min(1.0)  # (B, n)
    eye = torch.eye(n, dtype=u.dtype, device=u.device)
    copies = torch.cat([u[None] + eye[:, None, :] * step[None], u[None]])  # (n + 1, B, n)
    out = f(t, copies)
    f_u = out[n]
    df = (out[:n] - f_u[None]) / step.T[:, :, None]  # (n, B, n): [j, b, i]
    return f_u, df.permute(1, 2, 0)


def _fast_growth(step: RodasStep, J: torch.Tensor, h: float, atol: float) -> tuple[int, float] | None:
    """``(element, rate 1/s)`` when ``J`` has an eigenvalue with ``h Re(lambda) > 1``, else None.

    L-stable methods damp fast *growing* modes as they damp fast decaying ones, so a solution
    racing to a blow-up (a pole) can be stepped over with a small error estimate. Such steps
    change some element's state by more than half its size; only those elements' Jacobians are
    checked (eigenvalues cost about a step).
    """
    change = (step.u_new - step.u).detach().norm(dim=-1)  # (B,)
    size = step.u.detach().norm(dim=-1) + atol * step.u.shape[-1] ** 0.5
    suspect = torch.nonzero(change > 0.5 * size).flatten()
    if not suspect.numel():
        return None
    rates = torch.linalg.eigvals(J.detach()[suspect]).real.amax(-1)  # (S,) 1/s
    k = int(rates.argmax())
    rate = float(rates[k])
    return (int(suspect[k]), rate) if h * rate > 1.0 else None


def without_steps(t: torch.Tensor, u0: torch.Tensor) -> torch.Tensor | None:
    """``u`` at ``t (T,)`` where no step is needed (one time, or none passing): ``(T, B, n)``; else None."""
    if t.numel() == 1:
        return u0[None]
    if float(t[-1]) == float(t[0]):
        return torch.stack([u0] * t.numel())
    return None


def odeint_rodas(
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
    tableau: str = "rodas4",
) -> torch.Tensor:
    """Integrate ``du/dt = f(t, u)`` from ``u0 (B, n)`` and return ``u`` at times ``t (T,)``: ``(T, B, n)``.

    Same contract as :func:`~physmend.simulate.rosenbrock.odeint_rosenbrock`: ``t`` must be
    non-decreasing, ``t[0]`` is the initial time; ``tstops`` are times (s) where the right-hand
    side has kinks (knots of piecewise-linear inputs), on which steps end instead of straddling
    them (steps end on the evaluation times ``t`` as well); ``jacobian(t, u)`` gives
    ``df/du (B, n, n)`` exactly, otherwise forward differences in one broadcast call (``f`` must
    accept ``u (n + 1, B, n)``). All batch elements share the step size; the error norm is the
    RMS over states of ``err / (atol + rtol |u|)``, the largest over the batch; a step on which
    a mode grows faster than ``1/h`` is retried shorter (so blow-ups are not stepped over, see
    :func:`_fast_growth`). ``max_steps``
    counts attempted steps. ``tableau``: a name in :data:`~physmend.simulate.tableaus.TABLEAUS`. Raises
    :class:`SimulationError` naming the experiment (``names[b]``) and the time (s) when
    integration fails.
    """
    check_times(t)
    names = names or [str(i) for i in range(u0.shape[0])]
    t0, t_final = float(t[0]), float(t[-1])
    if (done := without_steps(t, u0)) is not None:
        return done
    tab = tableau_named(tableau)
    coefficients = _Coefficients(tab, u0)
    span = t_final - t0
    u = u0
    tc = t0
    h_min = 1e-14 * max(span, 1.0)
    # steps end on the kinks and on the evaluation times: returned values are the method's own
    # (error-controlled, order 4) step ends, never the order-3 interpolant, which can be far less
    # accurate where stiff states follow their inputs (long steps, tiny local error estimates)
    times = t.tolist()
    kinks = [] if tstops is None else tstops.detach().flatten().tolist()
    stops = sorted({x for x in [*kinks, *times] if t0 < x < t_final})
    next_stop = 0
    out = [u0]
    next_eval = 1
    steps = 0
    h: float | None = None if first_step is None else max(first_step, 10 * h_min)
    rejected = False
    fresh = True  # (tc, u) is a new point: f0, J and df/dt are evaluated there
    f0 = J = dfdt = u0
    while next_eval < len(times):
        tt = torch.as_tensor(tc, dtype=u.dtype, device=u.device)
        if fresh:
            if jacobian is not None:
                f0 = f(tt, u)
                _check_finite(f0, tc, names, "derivative")
                J = jacobian(tt, u)
            else:
                f0, J = _value_and_jacobian(f, tt, u)
                _check_finite(f0, tc, names, "derivative")
            if h is None:
                scale = atol + rtol * u.detach().abs()
                d0 = float((u.detach() / scale).pow(2).mean().sqrt())
                d1 = float((f0.detach() / scale).pow(2).mean().sqrt())
                h = 0.01 * d0 / d1 if d0 > 1e-5 and d1 > 1e-5 else 1e-6 * max(span, 1.0)
                h = max(min(span, h), 10 * h_min)
            delta = math.sqrt(torch.finfo(u.dtype).eps) * max(abs(tc), h)
            dfdt = (f(tt + delta, u) - f0) / delta  # forward difference: the input segment after tc
            fresh = False
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
        step = rodas_step(f, tt, u, h, f0, J, dfdt, tab, coefficients)
        scale = atol + rtol * torch.maximum(u.abs(), step.u_new.abs())
        per_elem = (step.err / scale).detach().pow(2).mean(-1).sqrt()
        err_norm = float(per_elem.max())  # NaN or inf if any element's is
        if not math.isfinite(err_norm):
            bad = [names[i] for i in torch.nonzero(~torch.isfinite(per_elem)).flatten().tolist()]
            h *= 0.25
            rejected = True
            if h < h_min:
                raise SimulationError(
                    f"integration failed for experiment(s) {bad} at t = {tc:.6g} s: the state or its "
                    "derivative became non-finite (NaN/inf)"
                )
            continue
        # the error estimate scales like h^order on acceptance; on rejection more like h^2.6
        # (stiff transients after input kinks): shrink with at least the cube root
        exponent = 1.0 / tab.order if err_norm <= 1.0 else max(1.0 / tab.order, 1.0 / 3.0)
        factor = min(6.0, max(0.2, 0.9 * err_norm**-exponent)) if err_norm > 0 else 6.0
        worst = int(per_elem.argmax())
        if err_norm <= 1.0:
            growth = _fast_growth(step, J, h, atol)
            if growth is not None:  # a mode grows faster than the step can follow: retry shorter
                worst, rate = growth
                h = min(h * factor, 0.5 / rate)
                rejected = True
                err_norm = math.inf
        if err_norm <= 1.0:
            t_new = tc + h
            while next_eval < len(times) and times[next_eval] <= t_new + 1e-12 * max(abs(t_new), 1.0):
                s = min(max((times[next_eval] - tc) / h, 0.0), 1.0)
                out.append(step.u_new if s == 1.0 else step.dense(s))
                next_eval += 1
            if rejected:
                factor = min(factor, 1.0)  # no growth right after a rejection
            h_next = h * factor
            u, tc = step.u_new, t_new
            if next_stop < len(stops) and abs(tc - stops[next_stop]) <= 1e-9 * max(abs(tc), 1.0):
                tc = stops[next_stop]  # landed on a kink: go on with at least the step wanted before it
                if factor >= 1.0:
                    h_next = max(h_next, h_wanted)
            h = h_next
            rejected = False
            fresh = True
        else:
            h *= factor
            rejected = True
        if h < h_min:
            raise SimulationError(
                f"integration failed for experiment {names[worst]!r} at t = {tc:.6g} s: step size "
                f"underflow ({h:.3g} s); the model is unstable or discontinuous there"
            )
    return torch.stack(out)
