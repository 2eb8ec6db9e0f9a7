"""Where the model as written misses: residual statistics per experiment and output, the windows
with the largest residuals, and the model variables and inputs the residual (and its drift rate)
correlate with. Correlations pool the training/validation experiments only; test experiments are
simulated to report their error."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import numpy as np

from physmend.explain import residuals as res
from physmend.problem import Problem
from physmend.settings import DiagnoseSettings
from physmend.simulate import Trajectories


def analyse(problem: Problem, traj: Trajectories, t: np.ndarray, cfg: Any) -> dict[str, Any]:
    """Residual statistics, worst windows and correlates as plain data (JSON-ready).

    ``traj``: the model as written simulated on every experiment of ``problem`` (batch element ``b``
    = experiment ``b``) on the time grid ``t (T,)``; ``cfg.diagnose``: ``window_fraction`` (a worst
    window's length as a share of the record), ``n_windows``, ``smooth_samples`` (the drift rate's
    smoothing) and ``n_correlates``. Returns ``fits`` (one dict per experiment and output),
    ``correlates`` (per output: ``residual`` and ``drift_rate`` correlates) and ``fit_experiments``."""
    dc = DiagnoseSettings.build(cfg.diagnose)
    model = problem.model
    outs = model.output_names
    sim = traj.outputs.detach().cpu().numpy()
    per: list[dict[str, Any]] = []
    fitted_roles = {"train", "validation"}
    aliases = redundant_observed(model)
    for b, exp in enumerate(problem.experiments):
        rows = np.searchsorted(t, exp.obs_time)
        span = float(exp.obs_time[-1] - exp.obs_time[0]) if exp.obs_time.size > 1 else 0.0
        for j, out in enumerate(outs):
            y = exp.obs[:, j]
            s = sim[rows, b, j]
            stats = res.error_stats(exp.obs_time, y, s)
            r = s - y
            windows = res.worst_windows(
                exp.obs_time, r, length=max(span * dc.window_fraction, 2 * interval(exp.obs_time)),
                count=dc.n_windows,
            )
            per.append(
                {
                    "experiment": exp.id,
                    "role": exp.role,
                    "output": out,
                    "unit": model.units.get(out, ""),
                    "span": span,
                    **stats.as_dict(),
                    "windows": [asdict(w) for w in windows],
                }
            )
    # correlates over training/validation experiments, pooled
    fit_idx = [b for b, e in enumerate(problem.experiments) if e.role in fitted_roles]
    states = traj.states.detach().cpu().numpy()
    observed = traj.observed.detach().cpu().numpy()
    inputs = traj.inputs.detach().cpu().numpy()
    corr: dict[str, Any] = {}
    for j, out in enumerate(outs):
        sig_r, sig_rate = [], []
        cands: dict[str, tuple[str, list[np.ndarray]]] = {}
        for b in fit_idx:
            exp = problem.experiments[b]
            rows = np.searchsorted(t, exp.obs_time)
            r = sim[rows, b, j] - exp.obs[:, j]
            sig_r.append(r)
            sig_rate.append(res.residual_rate(exp.obs_time, r, dc.smooth_samples))
            for i, name in enumerate(model.state_names):
                cands.setdefault(name, ("state", []))[1].append(states[rows, b, i])
            for i, name in enumerate(model.observed):
                if name not in aliases:
                    cands.setdefault(name, ("algebraic", []))[1].append(observed[rows, b, i])
            for i, name in enumerate(model.input_names):
                cands.setdefault(name, ("input", []))[1].append(inputs[rows, b, i])
        pooled = {k: (kind, np.concatenate(v)) for k, (kind, v) in cands.items()}
        n = dc.n_correlates
        corr[out] = {
            "residual": [asdict(c) for c in res.correlates(np.concatenate(sig_r), pooled, n)] if sig_r else [],
            "drift_rate": [asdict(c) for c in res.correlates(np.concatenate(sig_rate), pooled, n)] if sig_rate else [],
        }
    return {"fits": per, "correlates": corr, "fit_experiments": [problem.experiments[b].id for b in fit_idx]}


def redundant_observed(model: Any) -> set[str]:
    """Observed variables that repeat a state, an input, a constant or (±) another observed variable."""
    seen: set[Any] = {v.symbol for v in model.states} | {v.symbol for v in model.inputs}
    out: set[str] = set()
    for name, expr in model.observed.items():
        key = -expr if expr.could_extract_minus_sign() else expr
        if key in seen or not (expr.free_symbols - {v.symbol for v in model.parameters}):
            out.add(name)
        else:
            seen.add(key)
    return out


def interval(t: np.ndarray) -> float:
    """Median sampling interval of the times ``t (n,)`` (0 for fewer than two)."""
    gaps = np.diff(np.asarray(t, dtype=float))
    return float(np.median(gaps)) if gaps.size else 0.0
