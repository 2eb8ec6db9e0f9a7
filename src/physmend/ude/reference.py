"""The model as written, simulated on every experiment (the reference the network's inputs are
normalised from), the solver options, and the training/validation sample masks. Imports ``simulate``;
no other module of ``physmend.ude``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
import dataclasses
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch, SimulationError, make_batch, odeint
from physmend.simulate.batch import inputs_at, own_stops
from physmend.simulate.core import CLOCK_METHODS, OWN_METHODS
from physmend.simulate.initial import estimate_initial, has_unknown


@dataclass
class Reference:
    """The model as written, simulated on every experiment (no gradients)."""

    batch: Batch
    states: torch.Tensor  # (T, B, n)
    derivs: torch.Tensor  # (T, B, n)
    inputs: torch.Tensor  # (T, B, m)
    observed: torch.Tensor  # (T, B, k)


def _sim_opts(cfg: Any) -> dict[str, Any]:
    return {
        "method": str(cfg.simulate.method),
        "rtol": float(cfg.simulate.rtol),
        "atol": float(cfg.simulate.atol),
        "options": dict(cfg.simulate.get("options") or {}),
    }


def _kinks(batch: Batch, method: str) -> dict[str, Any]:
    knots = batch.inputs.knots
    inner = knots[(knots > batch.t[0]) & (knots < batch.t[-1])]
    if not inner.numel():
        return {}
    return {"tstops": inner} if method in OWN_METHODS else {"step_t": inner}


def simulate_with(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], batch: Batch, u0: torch.Tensor, sim: dict[str, Any],
                  jac: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Whole-trajectory simulation of ``rhs(u, x)`` on ``batch``: states ``(T, B, n)``.

    ``jac(u, x)``: the exact ``d rhs / du (B, n, n)``, used by the stiff solver instead of finite
    differences (which cost ``n`` extra right-hand sides per step).
    """
    options = {**_kinks(batch, sim["method"]), **sim["options"]}
    if sim["method"] in CLOCK_METHODS and "clocks" not in options:
        options["clocks"] = own_stops(batch)  # each experiment steps on its own times only (None: shared)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return rhs(u, inputs_at(batch, t))

    if jac is not None and sim["method"] in OWN_METHODS and "jacobian" not in options:
        options["jacobian"] = lambda t, u: jac(u, inputs_at(batch, t))

    return odeint(f, u0, batch.t, method=sim["method"], rtol=sim["rtol"], atol=sim["atol"], options=options, names=batch.ids)


def reference(problem: Problem, cfg: Any) -> Reference:
    model = problem.compiled
    batch = make_batch(problem.experiments, model, problem.dtype)

    # one shared clock: the reference's values at every row of the shared axis (the network's
    # normalisation, segment starts of hidden states) are the method's step ends, not interpolants
    sim = _sim_opts(cfg)
    sim = {**sim, "options": {**sim["options"], "clocks": None}}

    def outputs(sub: Batch, u0: torch.Tensor) -> torch.Tensor:
        states = simulate_with(model.bind(sub.params), sub, u0, sim, model.jacobian(sub.params))
        return model.outputs(states, sub.inputs.at(sub.t), sub.params[None])

    def solve(sub: Batch) -> torch.Tensor:
        rhs = model.bind(sub.params)
        return simulate_with(rhs, sub, sub.u0, sim, model.jacobian(sub.params))

    with torch.no_grad():
        if has_unknown(batch):  # declared-unknown initial values: the model as written's own estimates
            batch = dataclasses.replace(batch, u0=estimate_initial(outputs, batch, model.state_names))
        states = held_out_apart(problem, batch, solve)
        rhs = model.bind(batch.params)
        x = batch.inputs.at(batch.t)
        derivs = rhs(states, x)
        observed = model.observed(states, x, batch.params[None])
    return Reference(batch, states, derivs, x, observed)


def held_out_apart(problem: Problem, batch: Batch, solve: Callable[[Batch], torch.Tensor]) -> torch.Tensor:
    """``solve(batch)`` — a whole-trajectory quantity ``(T, B, ...)`` — on every experiment, such that
    test experiments decide nothing: when the one solve fails, the training and validation
    experiments are solved together (their failure is raised) and each test experiment alone; a
    test experiment whose solve fails is NaN throughout.
    """
    try:
        return solve(batch)
    except SimulationError as exc:
        first = exc
        test = [i for i, e in enumerate(problem.experiments) if e.role == "test"]
        if not test:
            raise
    kept = [i for i in range(batch.size) if i not in test]
    u0 = {int(i): batch.u0[i] for i in range(batch.size)}
    out: torch.Tensor | None = None
    for group in [kept] + [[i] for i in test]:
        if not group:
            continue
        sub = make_batch([problem.experiments[i] for i in group], problem.compiled, problem.dtype)
        sub = dataclasses.replace(sub, u0=torch.stack([u0[i] for i in group]))  # estimated starts stay
        try:
            part = solve(sub)
        except SimulationError:
            if group is kept:
                raise
            continue  # NaN: the report counts it (test.failed)
        if out is None:
            out = torch.full((batch.t.shape[0], batch.size, *part.shape[2:]), math.nan, dtype=part.dtype)
        out[:, torch.tensor(group)] = on_axis(part, sub.t, batch.t)
    if out is None:  # only test experiments, and none could be solved
        raise first
    return out


def on_axis(values: torch.Tensor, t_from: torch.Tensor, t_to: torch.Tensor) -> torch.Tensor:
    """``values (T1, ...)`` at the times ``t_from (T1,)`` (ascending), linearly interpolated to the
    times ``t_to (T2,)``: ``(T2, ...)``, NaN outside ``t_from``'s span (a group solved apart has no
    rows at the other experiments' sample times; every row of the shared axis needs its value)."""
    k = torch.searchsorted(t_from, t_to).clamp(1, max(t_from.shape[0] - 1, 1))
    if t_from.shape[0] == 1:
        out = values[torch.zeros_like(k)]
    else:
        t0, t1 = t_from[k - 1], t_from[k]
        w = ((t_to - t0) / (t1 - t0)).reshape(-1, *([1] * (values.dim() - 1))).to(values.dtype)
        out = values[k - 1] + w * (values[k] - values[k - 1])
    outside = (t_to < t_from[0]) | (t_to > t_from[-1])
    return torch.where(outside.reshape(-1, *([1] * (values.dim() - 1))), torch.nan, out)


def _train_mask(problem: Problem, batch: Batch) -> torch.Tensor:
    """``(T, B)`` True where a time belongs to a training sample (train role, before the split)."""
    roles = torch.tensor([e.role == "train" for e in problem.experiments])
    return (batch.t[:, None] < batch.split_time[None, :]) & roles[None, :]


def _val_mask(problem: Problem, batch: Batch) -> torch.Tensor:
    if any(e.role == "validation" for e in problem.experiments):
        roles = torch.tensor([e.role == "validation" for e in problem.experiments])
        return roles[None, :].expand(batch.t.shape[0], -1).clone()
    roles = torch.tensor([e.role == "train" for e in problem.experiments])
    return (batch.t[:, None] >= batch.split_time[None, :]) & roles[None, :]


def _stats(values: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and std over masked ``(T, B)`` entries of ``values (T, B, k)``; std floored."""
    v = values[mask]
    mean = v.mean(0)
    std = v.std(0) if v.shape[0] > 1 else torch.ones_like(mean)
    floor = 1e-3 * mean.abs().clamp_min(1.0)
    return mean, torch.where(std < floor, torch.maximum(floor, torch.ones_like(std) * (std < 1e-12)), std)
