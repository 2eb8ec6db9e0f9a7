"""Derivative-matching (collocation) warm start of a hybrid model, where the outputs allow it.

When some outputs are plain states (``y_j = u_i``), their smoothed records give both the state and
its rate of change. The hidden states are then simulated with the measured ones *forced* to their
smoothed records (so walls, masses, … follow the real temperatures, positions, …), and the
mismatch of each measured state's equation is known at every grid point:

    r_i(t) = dŷ_i/dt − f_i(û(t), x(t), p)        [state unit / s]

Fitting the network to ``r`` (and the other corrections to zero) is plain regression — no ODE
solve, a second or two — and gives multiple shooting a network and segment starts close to a good
fit. Models whose outputs are not states get no warm start.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from physmend.problem import Problem
from physmend.simulate import Batch
from physmend.ude.hybrid import HybridModel


@dataclass
class Forced:
    """Training experiments on a uniform grid with measured states forced to their smoothed records.

    Shapes: ``G`` grid points (step ``dt`` s from 0), ``E`` training experiments.
    """

    dt: float
    exp_index: torch.Tensor  # (E,) batch element of each training experiment
    states: torch.Tensor  # (G, E, n) û: measured states smoothed, hidden states simulated
    rates: torch.Tensor  # (G, E, q) dŷ/dt of the measured states
    inputs: torch.Tensor  # (G, E, m)
    valid: torch.Tensor  # (G, E) True where a grid point lies inside the training record, near samples
    measured: list[int]  # the q measured state indices (model order)


def measured_states(problem: Problem) -> list[tuple[int, int]]:
    """``(output index, state index)`` for every output that measures one state: the state itself
    or the state times a factor of the parameters (:mod:`physmend.ude.measured`)."""
    from physmend.ude.measured import measured_outputs

    return [(j, i) for j, i, _ in measured_outputs(problem.model)]


#: grid points per weak-form window in the warm-start regression: longer windows use every k-th point
#: of the training grid (the rates are window means, smooth on that scale; the network is evaluated
#: on 1/k of the rows)
QUADRATURE_POINTS = 10

_SMOOTHED: dict[str, tuple[np.ndarray, np.ndarray]] = {}
_SMOOTHED_MAX = 64  # cached splines (each a few grids of floats): sweeps and stages refit the same records


def _smooth(t: np.ndarray, y: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothing spline (smoothness by generalised cross-validation): value and slope on ``grid``.

    The result depends only on the three arrays, so it is cached by their contents: every trial of
    a sweep (and the symbolic stage) smooths the same records, and the GCV fit costs ~0.3 s each.
    """
    from scipy.interpolate import make_smoothing_spline

    key = hashlib.sha1(b"".join(np.ascontiguousarray(a, dtype=float).tobytes() + b"|" for a in (t, y, grid))).hexdigest()
    hit = _SMOOTHED.get(key)
    if hit is None:
        spline = make_smoothing_spline(t, y)
        g = np.clip(grid, t[0], t[-1])
        hit = (spline(g), spline.derivative()(g) * ((grid >= t[0]) & (grid <= t[-1])))
        if len(_SMOOTHED) >= _SMOOTHED_MAX:
            _SMOOTHED.pop(next(iter(_SMOOTHED)))
        _SMOOTHED[key] = hit
    return hit[0].copy(), hit[1].copy()


def forced_trajectories(problem: Problem, batch: Batch, hybrid: HybridModel, dt: float) -> Forced | None:
    """Smooth the measured states and simulate the rest with them forced (fixed-step RK4, step ``dt`` s).

    Returns None when no output measures a state (nothing to match).
    """
    pairs = measured_states(problem)
    train = [b for b, e in enumerate(problem.experiments) if e.role == "train"]
    if not pairs or not train:
        return None
    ends = [float(problem.experiments[b].split_time if problem.experiments[b].split_time is not None
                  else problem.experiments[b].obs_time[-1]) for b in train]
    steps = int(math.ceil(max(ends) / dt - 1e-9))
    fine = np.arange(2 * steps + 1) * (dt / 2)  # grid and half steps
    q = len(pairs)
    y_hat = np.zeros((fine.size, len(train), q))
    dy_hat = np.zeros_like(y_hat)
    valid = np.zeros((fine.size, len(train)), dtype=bool)
    for e, b in enumerate(train):
        exp = problem.experiments[b]
        t = np.asarray(exp.obs_time, dtype=float)
        near = np.zeros(fine.size, dtype=bool)
        for c, (j, _) in enumerate(pairs):
            y = np.asarray(exp.obs[:, j], dtype=float)
            ok = np.isfinite(y) & (t < ends[e])
            if ok.sum() < 10:
                return None
            y_hat[:, e, c], dy_hat[:, e, c] = _smooth(t[ok], y[ok], fine)
            spacing = float(np.median(np.diff(t[ok])))
            idx = np.clip(np.searchsorted(t[ok], fine), 1, ok.sum() - 1)
            gap = np.minimum(np.abs(fine - t[ok][idx - 1]), np.abs(t[ok][idx] - fine))
            near_c = (gap <= 2 * spacing) & (fine >= t[ok][0]) & (fine <= ends[e])
            near = near_c if c == 0 else near & near_c
        valid[:, e] = near
    dtype = batch.t.dtype
    sel = torch.tensor(train)
    from physmend.ude.measured import factors

    with torch.no_grad():  # an output y = g(p)·x records the state x = y / g(p), per experiment
        g = factors(problem.model)(hybrid.parameters_for(batch.params[sel]))[None]  # (1, E, q)
    yh = torch.as_tensor(y_hat, dtype=dtype) / g
    dyh = torch.as_tensor(dy_hat, dtype=dtype) / g
    x_fine = batch.inputs.select(sel).at(torch.as_tensor(fine, dtype=dtype))  # (2G-1, E, m)
    idx = torch.tensor([i for _, i in pairs])
    with torch.no_grad():
        p = hybrid.parameters_for(batch.params[sel])
        physics = hybrid.compiled.bind(p)

        def f(u: torch.Tensor, k: int) -> torch.Tensor:
            u = u.index_copy(-1, idx, yh[k])
            return physics(u, x_fine[k]).index_copy(-1, idx, dyh[k])

        u = batch.u0[sel].index_copy(-1, idx, yh[0])
        out = [u]
        for s in range(steps):
            k = 2 * s
            k1 = f(u, k)
            k2 = f(u + 0.5 * dt * k1, k + 1)
            k3 = f(u + 0.5 * dt * k2, k + 1)
            k4 = f(u + dt * k3, k + 2)
            u = (u + (dt / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)).index_copy(-1, idx, yh[k + 2])
            out.append(u)
        states = torch.stack(out)
    if not bool(torch.isfinite(states).all()):
        return None
    return Forced(dt=dt, exp_index=sel, states=states, rates=dyh[0::2], inputs=x_fine[0::2],
                  valid=torch.as_tensor(valid[0::2]), measured=idx.tolist())


def fit_network(hybrid: HybridModel, problem: Problem, batch: Batch, forced: Forced, *, iterations: int = 400,
                lr: float = 0.01, window: int = 1) -> dict[str, float]:
    """Fit the network (and jointly estimated parameters) to the measured states' equation mismatch.

    Corrections of hidden equations are pulled towards zero (in units of their state's typical
    derivative). Returns ``{"warm.loss": …, "warm.r2": …}`` (R² of the measured mismatch).
    """
    p_exp = batch.params[forced.exp_index]  # (E, n_params): physics bound once per experiment
    params = list(hybrid.net.parameters()) + ([hybrid.est_raw] if hybrid.est_idx else [])
    stats = fit_models(problem, forced, hybrid.corrected_idx, models=1,
                       corrections=hybrid.corrections, parameters=lambda: hybrid.parameters_for(p_exp),
                       typical=hybrid.rate_scale[None], params=params, iterations=iterations, lr=lr, window=window)
    return {k: float(v[0]) for k, v in stats.items()}


def fit_models(problem: Problem, forced: Forced, corrected: Sequence[int], *, models: int,
               corrections: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
               parameters: Callable[[], torch.Tensor], typical: torch.Tensor, params: Sequence[torch.Tensor],
               masks: Sequence[torch.Tensor | None] | None = None, iterations: int = 400, lr: float = 0.01,
               window: int = 1) -> dict[str, torch.Tensor]:
    """The warm-start regression of ``models`` independent hybrid models at once (see :func:`fit_network`).

    Rows are model-major: ``parameters()`` gives ``(models·E, n_params)`` (each model's estimates,
    ``E`` training experiments), ``corrections(u, x, p)`` maps ``u (G, models·E, n)``,
    ``x (G, models·E, m)`` to ``(G, models·E, k)`` for the ``k`` corrected equations (state indices
    ``corrected``); ``typical (models, k)`` is each correction's initial size (state unit / s).
    Each model's loss depends only on its own rows, and Adam acts element-wise, so every model is
    fitted exactly as it would be alone; ``masks`` (same layout as ``params``, None = all) zero the
    gradients of entries that must not move (padding). Returns ``warm.loss`` and ``warm.r2``, ``(models,)``.
    """
    meas_cols = [corrected.index(i) for i in forced.measured if i in corrected]
    meas_idx = [i for i in forced.measured if i in corrected]
    if not meas_cols:
        return {}
    hidden_cols = [c for c in range(len(corrected)) if c not in meas_cols]
    w = max(1, int(window))
    thin = max(1, w // QUADRATURE_POINTS)
    if thin > 1:  # window means from every thin-th grid point: the same weak form, a fraction of the rows
        forced = dataclasses.replace(forced, states=forced.states[::thin], rates=forced.rates[::thin],
                                     inputs=forced.inputs[::thin], valid=forced.valid[::thin])
        w = max(1, round(w / thin))
    m, e = models, forced.valid.shape[1]

    def box(a: torch.Tensor) -> torch.Tensor:
        """Mean over windows of ``w`` grid points along time (the weak form of the rate match)."""
        if w == 1:
            return a
        c = torch.cat([torch.zeros_like(a[:1]), a.cumsum(0)])
        return (c[w:] - c[:-w]) / w

    def per_model(a: torch.Tensor) -> torch.Tensor:
        """``(G, models·E, c)`` summed over time, experiments and columns: ``(models,)``."""
        return a.reshape(a.shape[0], m, e, a.shape[-1]).sum(dim=(0, 2, 3))

    v_point = forced.valid.to(forced.states.dtype).repeat(1, m)[..., None]  # (G, models·E, 1)
    v = (box(v_point) > 1 - 1e-9).to(v_point.dtype)
    count = v[:, :e].sum().clamp_min(1.0)  # the same for every model
    n_point = v_point[:, :e].sum().clamp_min(1.0)
    u, x = forced.states.repeat(1, m, 1), forced.inputs.repeat(1, m, 1)  # (G, models·E, n), (G, models·E, m)
    rate = forced.rates[..., [forced.measured.index(i) for i in meas_idx]].repeat(1, m, 1)
    typical = typical.clamp_min(1e-30).repeat_interleave(e, 0)  # (models·E, k)

    def mismatch(p: torch.Tensor) -> torch.Tensor:
        return rate - problem.compiled.bind(p)(u, x)[..., meas_idx]

    def by_model(a: torch.Tensor) -> torch.Tensor:  # (G, models·E, c) -> (G, models, E, c)
        return a.reshape(a.shape[0], m, e, a.shape[-1])

    with torch.no_grad():
        r0 = by_model(box(mismatch(parameters())))
        vm = by_model(v)
        r_mean = (r0 * vm).sum((0, 2), keepdim=True) / count  # (1, models, 1, q)
        r_scale = (((r0 - r_mean) ** 2 * vm).sum((0, 2), keepdim=True) / count).sqrt().clamp_min(1e-12)
    opt = torch.optim.Adam(list(params), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=iterations)
    loss = torch.zeros(m)
    fixed = None if parameters().requires_grad else mismatch(parameters())  # no parameter estimated: one physics evaluation
    for _ in range(iterations):
        opt.zero_grad(set_to_none=True)
        p = parameters()
        corr = corrections(u, x, p)
        res = by_model(box(corr[..., meas_cols] - (mismatch(p) if fixed is None else fixed))) / r_scale
        loss = per_model((res**2 * vm).flatten(1, 2)) / (count * len(meas_cols))
        if hidden_cols:
            hidden = (corr[..., hidden_cols] / typical[:, hidden_cols]) ** 2 * v_point
            loss = loss + per_model(hidden) / (n_point * len(hidden_cols))
        loss.sum().backward()
        if masks is not None:
            for t, mk in zip(params, masks):
                if mk is not None and t.grad is not None:
                    t.grad.mul_(mk)
        opt.step()
        sched.step()
    with torch.no_grad():
        p = parameters()
        r = by_model(box(mismatch(p)))
        res = (r - by_model(box(corrections(u, x, p)[..., meas_cols]))) * vm
        total = (((r - r_mean) * vm) ** 2).sum(dim=(0, 2, 3)).clamp_min(1e-30)
        r2 = 1.0 - res.pow(2).sum(dim=(0, 2, 3)) / total
    return {"warm.loss": loss.detach(), "warm.r2": r2}


def segment_starts(forced: Forced, exp_index: torch.Tensor, starts: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """Multiple-shooting segment starts ``(S, n)`` from the forced trajectories (``fallback`` elsewhere)."""
    out = fallback.clone()
    where = {int(b): e for e, b in enumerate(forced.exp_index.tolist())}
    for s in range(starts.shape[0]):
        e = where.get(int(exp_index[s]))
        k = int(round(float(starts[s]) / forced.dt))
        if e is not None and k < forced.states.shape[0]:
            out[s] = forced.states[k, e]
    return out


# -- reuse ------------------------------------------------------------------------------------------
#: warm-start results of this process, by :func:`warm_key`: sweep trials that share an architecture and
#: a seed (they differ in learning rate, weight decay …) start from the same fitted network
_WARM: dict[str, tuple[Any, dict[str, torch.Tensor]]] = {}
_WARM_MAX = 256
#: what else follows from a stored warm start alone, by key and name (its checkpoint evaluation,
#: its chained segment starts on one shooting plan): computed once, reused by later trials
_DERIVED: dict[str, dict[Any, Any]] = {}
#: how many warm starts this process fitted and how many it reused (for tests and benchmarks)
WARM_STATS = {"fitted": 0, "reused": 0, "derived_reused": 0}


def warm_key(hybrid: HybridModel, forced: Forced, params: torch.Tensor, iterations: int, window: int) -> str:
    """Everything a warm start's result depends on, hashed: the hybrid as initialised (spec,
    weights, estimates, normalisation, output mask), the forced trajectories, the experiments'
    parameters ``params (E, n_params)``, the regression settings, and the compiled model itself."""
    h = hashlib.sha1()
    h.update(json.dumps(hybrid.spec.to_dict(), sort_keys=True, default=str).encode())
    tensors = [t for _, t in sorted(hybrid.state_dict().items())] + [hybrid.out_mask]
    tensors += [forced.states, forced.rates, forced.inputs, forced.valid, params]
    for t in tensors:
        h.update(np.ascontiguousarray(t.detach().cpu().numpy()).tobytes() + b"|")
    h.update(f"{iterations}|{window}|{forced.dt}|{forced.measured}|{id(hybrid.compiled)}|{params.device}".encode())
    return h.hexdigest()


def same_warm_start(keys: Sequence[str | None]) -> list[int]:
    """For each position of ``keys`` (:func:`warm_key`, None: none), the first position with the same
    key, its own where the key is None: models of one warm start (trials that differ in their training
    settings only) whose checks, chained starts or first evaluation are one model's."""
    firsts: dict[str, int] = {}
    return [i if key is None else firsts.setdefault(key, i) for i, key in enumerate(keys)]


def recall(key: str, hybrid: HybridModel) -> bool:
    """Load the warm start stored under ``key`` into ``hybrid``; False when there is none."""
    hit = _WARM.get(key)
    if hit is None or hit[0] is not hybrid.compiled:
        return False
    hybrid.load_state_dict(hit[1])
    WARM_STATS["reused"] += 1
    return True


def remember(key: str, hybrid: HybridModel) -> None:
    """Store ``hybrid``'s warm-started state under ``key`` (the oldest entry goes when full)."""
    if len(_WARM) >= _WARM_MAX:
        oldest = next(iter(_WARM))
        _WARM.pop(oldest)
        _DERIVED.pop(oldest, None)
    _WARM[key] = (hybrid.compiled, {k: v.detach().clone() for k, v in hybrid.state_dict().items()})
    WARM_STATS["fitted"] += 1


def recall_derived(key: str, name: Any) -> Any | None:
    """What :func:`remember_derived` stored for the warm start ``key`` under ``name``; None if nothing."""
    value = _DERIVED.get(key, {}).get(name)
    if value is not None:
        WARM_STATS["derived_reused"] += 1
    return value


def remember_derived(key: str, name: Any, value: Any) -> None:
    """Store ``value``, computed from the warm start ``key`` alone (nothing a trial's own training
    settings change), under ``name``: kept as long as the warm start itself."""
    if key in _WARM:
        _DERIVED.setdefault(key, {})[name] = value


def forget_warm_starts() -> None:
    """Drop every stored warm start and what was derived from it (tests that compare two ways of computing one)."""
    _WARM.clear()
    _DERIVED.clear()


def warm_start(hybrid: HybridModel, problem: Problem, batch: Batch, cfg: Any) -> Forced | None:
    """Collocation warm start per ``cfg.train.warm_start`` (``auto`` | ``none``); the forced trajectories or None."""
    from physmend.settings import training_settings

    cfg = training_settings(cfg)
    if cfg.train.warm_start == "none":
        return None
    from physmend.ude.timescale import resolve_settings

    cfg = resolve_settings(cfg, problem)
    forced = forced_trajectories(problem, batch, hybrid, float(cfg.train.step))
    if forced is None:
        return None
    window = cfg.train.warm_window_steps
    iterations = cfg.train.warm_iterations
    key = warm_key(hybrid, forced, batch.params[forced.exp_index], iterations, window)
    if not recall(key, hybrid):
        fit_network(hybrid, problem, batch, forced, iterations=iterations, window=window)
        remember(key, hybrid)
    return forced
