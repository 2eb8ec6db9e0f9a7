"""What the recordings say each measured equation is missing, to judge candidate formulas by.

A formula fitted to a trained network inherits the network's quirks (offsets it absorbed, proxies
it leaned on). The recordings give an independent check wherever an equation's state is measured:
along the forced trajectories of the warm start (:mod:`physmend.ude.warmstart`) the equation's
mismatch is known from data alone,

    M_i(t) = a_i · ( dŷ_i/dt − f_i(û, x, p) )        [equation units, e.g. W],

averaged over windows (``symbolic.window`` seconds) (weak form: the noise of a differentiated
record averages out). A candidate term ``g`` is scored by how much of ``M_i`` it explains once
scaled by its best factor ``α``; no ODE is solved.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy as sp
import torch

from physmend.problem import Problem
from physmend.simulate import make_batch
from physmend.ude.hybrid import HybridModel
from physmend.ude.warmstart import forced_trajectories


@dataclass
class RecordedRates:
    """Weak-form mismatch of the measured equations along the forced training trajectories.

    Shapes: ``G`` grid points, ``E`` training experiments, ``W`` windows (``G - window + 1``).
    """

    columns: dict[str, np.ndarray]  # variable (state, input, parameter) -> (G, E) values
    targets: dict[str, np.ndarray]  # corrected state -> (W, E) mismatch in its equation's units
    valid: np.ndarray  # (W, E) windows lying wholly inside the records
    window: int  # grid points per window

    def box(self, values: np.ndarray) -> np.ndarray:
        """Window means ``(W, E)`` of pointwise values ``(G, E)`` (or a scalar)."""
        values = np.broadcast_to(np.asarray(values, dtype=float), next(iter(self.columns.values())).shape)
        c = np.concatenate([np.zeros_like(values[:1]), np.cumsum(values, axis=0)])
        return (c[self.window:] - c[:-self.window]) / self.window

    def score(self, expr: sp.Expr, state: str) -> tuple[float, float, float]:
        """``(α, MSE, R²)`` of ``α·expr`` against the recorded mismatch of ``state``'s equation."""
        from physmend.modeling.evaluate import evaluate, mse_r2

        shape = next(iter(self.columns.values())).shape
        used = expr.free_symbols  # a walk of the whole expression: once, not once per column
        flat = {k: v.ravel() for k, v in self.columns.items() if sp.Symbol(k) in used}
        g = self.box(evaluate(expr, flat, n=int(np.prod(shape))).reshape(shape))[self.valid]
        y = self.targets[state][self.valid]
        ok = np.isfinite(g)
        if ok.sum() < 2:
            return float("nan"), float("inf"), float("-inf")
        gg = float(g[ok] @ g[ok])
        alpha = float(g[ok] @ y[ok]) / gg if gg > 0 else 0.0
        mse, r2 = mse_r2(y[ok], alpha * g[ok])
        return alpha, mse, r2


def recorded_rates(hybrid: HybridModel, problem: Problem, cfg: Any, states: list[str], window_s: float,
                   handed: list[str] = ()) -> RecordedRates | None:
    """The recorded mismatch of each equation in ``states`` whose state is measured, averaged over
    windows of ``window_s`` seconds, with the estimates ``handed`` back at their declared values
    (:func:`physmend.ude.analysis.absorbed`); None when no state of ``states`` is measured."""
    from physmend.modeling.compile import lambdify_torch

    from physmend.ude.timescale import resolved

    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    dt = float(resolved(cfg, problem).train.step)
    forced = forced_trajectories(problem, batch, hybrid, dt)
    if forced is None:
        return None
    names = problem.model.state_names
    wanted = [s for s in states if names.index(s) in forced.measured]
    if not wanted:
        return None
    window = max(1, int(round(float(window_s) / dt)))
    # the estimates, but those that absorbed missing physics back at their declared values (what they
    # changed then shows in the mismatch, as in the symbolic target) (E, n_params)
    from physmend.ude.analysis import handed_back

    p = handed_back(hybrid, problem, batch.params[forced.exp_index], list(handed))
    with torch.no_grad():
        physics = problem.compiled.bind(p)(forced.states, forced.inputs)  # (G, E, n)
    psyms = [v.symbol for v in problem.model.parameters]
    columns: dict[str, np.ndarray] = {}
    for i, n in enumerate(names):
        columns[n] = forced.states[..., i].cpu().numpy()
    for j, n in enumerate(problem.model.input_names):
        columns[n] = forced.inputs[..., j].cpu().numpy()
    G = forced.states.shape[0]
    for k, n in enumerate(problem.model.parameter_names):
        columns[n] = np.broadcast_to(p[:, k].cpu().numpy(), (G, p.shape[0])).copy()
    with torch.no_grad():  # algebraic variables too (a formula may act on a recorded concentration)
        observed = problem.compiled.observed(forced.states, forced.inputs, p[None])
    for k, n in enumerate(problem.compiled.observed_names):
        columns.setdefault(n, observed[..., k].cpu().numpy())
    rates = RecordedRates(columns=columns, targets={}, valid=np.zeros(0, dtype=bool), window=window)
    point_valid = forced.valid.cpu().numpy().astype(float)
    rates.valid = rates.box(point_valid) > 1 - 1e-9
    for s in wanted:
        i = names.index(s)
        coef = lambdify_torch(psyms, [problem.model.der_coefficient[s]], "der coefficient")(*p.unbind(-1))[0]
        a = torch.as_tensor(coef, dtype=p.dtype).expand(p.shape[0]).cpu().numpy()  # (E,)
        mismatch = (forced.rates[..., forced.measured.index(i)] - physics[..., i]).cpu().numpy() * a[None, :]
        rates.targets[s] = rates.box(mismatch)
    return rates
