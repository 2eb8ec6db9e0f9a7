"""Training a hybrid model: multiple shooting on the training records, honest evaluation.

Training solves every segment of every training experiment in one batched fixed-step RK4
solve (segment starts are trainable, a continuity penalty joins them; the first segment of each
experiment starts from its known initial state). Every reported metric comes from simulating
whole trajectories (single shooting, adaptive stiff solver) — never from the segments.

Validation: validation experiments if the data config has any, otherwise the carved last part of
each training record (``split_time``); training never sees those samples.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from physmend.problem import Problem
from physmend.simulate import Batch, SimulationError, make_batch, odeint
from physmend.simulate.core import OWN_METHODS
from physmend.ude.hybrid import HybridModel, HybridSpec, UDEConfigError, match_names
from physmend.ude.warmstart import segment_starts, warm_start


class TrainingDiverged(RuntimeError):
    """Training produced non-finite losses or trajectories; the message says when and why."""


@dataclass
class TrainResult:
    """Outcome of one training run (see :func:`train`)."""

    val_rmse: float
    metrics: dict[str, float]
    history: list[dict[str, float]]
    artifacts: dict[str, str | bytes]
    figures: dict[str, Any] = field(default_factory=dict)
    hybrid: HybridModel | None = None


# -- reference simulation, normalisation ---------------------------------------------------------
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

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return rhs(u, batch.inputs(t))

    if jac is not None and sim["method"] in OWN_METHODS and "jacobian" not in options:
        options["jacobian"] = lambda t, u: jac(u, batch.inputs(t))

    return odeint(f, u0, batch.t, method=sim["method"], rtol=sim["rtol"], atol=sim["atol"], options=options, names=batch.ids)


def reference(problem: Problem, cfg: Any) -> Reference:
    model = problem.compiled
    batch = make_batch(problem.experiments, model, problem.dtype)
    with torch.no_grad():
        rhs = model.bind(batch.params)
        states = simulate_with(rhs, batch, batch.u0, _sim_opts(cfg), model.jacobian(batch.params))
        x = batch.inputs.at(batch.t)
        derivs = rhs(states, x)
        observed = model.observed(states, x, batch.params[None])
    return Reference(batch, states, derivs, x, observed)


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


MIN_PARAMETER_VALUES = 3
"""A parameter is a network (and formula) input under ``auto`` when it takes at least this many
distinct values across the training experiments: with two, it only tells the experiments apart (an
experiment label that lets the network memorise per-experiment offsets); from three on, a smooth
dependence on it is what fits."""


def informative_parameters(problem: Problem, min_values: int = MIN_PARAMETER_VALUES) -> list[str]:
    """Parameters that take at least ``min_values`` distinct values across the training experiments."""
    train = [e for e in problem.experiments if e.role == "train"]
    if len(train) < min_values:
        return []
    values = np.stack([np.asarray(e.parameters, dtype=float) for e in train])  # (E, n_params)
    out = []
    for j, name in enumerate(problem.model.parameter_names):
        col = values[:, j]
        tol = 1e-9 * max(float(np.abs(col).max()), 1.0)
        distinct = np.unique(np.round(col / tol)) if tol > 0 else np.unique(col)
        if distinct.size >= min_values:
            out.append(name)
    return out


def identity_states(problem: Problem) -> list[str]:
    """States whose equation is a definition, ``der(x) = y`` with ``y`` another state (a position and
    its velocity): nothing physical can be missing from it, so a correction there could only be a
    solver artefact standing in for physics missing elsewhere (the seed paper's dummy derivatives)."""
    model = problem.model
    states = set(model.state_names)
    out = []
    for name in model.state_names:
        rhs, coef = model.rhs.get(name), model.der_coefficient.get(name, 1)
        if rhs is not None and getattr(rhs, "is_Symbol", False) and rhs.name in states and rhs.name != name \
                and coef == 1:
            out.append(name)
    return out


def build_spec(cfg: Any, problem: Problem, ref: Reference) -> HybridSpec:
    """Choose corrected equations and network inputs from ``cfg.ude``; normalise from ``ref``.

    ``ude.corrected`` patterns select the corrected equations; a pattern that is a wildcard (``*``)
    leaves out definitional equations (:func:`identity_states`); naming one corrects it."""
    ude = cfg.ude
    model = problem.model
    corrected = match_names(list(ude.corrected), model.state_names, "ude.corrected")
    named = {str(p) for p in ude.corrected}
    corrected = [n for n in corrected if n in named or n not in identity_states(problem)]
    sel = ude.inputs
    in_states = model.state_names if bool(sel.states) else []
    in_observed = match_names(list(sel.observed or []), list(model.observed), "ude.inputs.observed")
    in_inputs = model.input_names if bool(sel.inputs) else []
    if isinstance(sel.parameters, str):
        if sel.parameters != "auto":
            raise UDEConfigError(f"ude.inputs.parameters must be 'auto' or a list of names/patterns, but got {sel.parameters!r}")
        in_params = informative_parameters(problem)
    else:
        in_params = match_names(list(sel.parameters or []), model.parameter_names, "ude.inputs.parameters")
    if not (in_states or in_observed or in_inputs or in_params):
        raise UDEConfigError("ude.inputs selects no network input; enable states, inputs, observed or parameters")
    estimated = [v.name for v in model.parameters if v.uncertain] if bool(cfg.train.estimate_parameters) else []
    widths = [int(ude.width)] * int(ude.depth)
    mask = _train_mask(problem, ref.batch)
    cm = problem.compiled
    feats = [ref.states[..., [cm.state_names.index(n) for n in in_states]]]
    if in_observed:
        feats.append(ref.observed[..., [cm.observed_names.index(n) for n in in_observed]])
    if in_inputs:
        feats.append(ref.inputs[..., [cm.input_names.index(n) for n in in_inputs]])
    if in_params:
        p = ref.batch.params[:, [cm.parameter_names.index(n) for n in in_params]]
        feats.append(p[None].expand(ref.states.shape[0], -1, -1))
    mean, std = _stats(torch.cat(feats, -1), mask)
    d = ref.derivs[..., [cm.state_names.index(n) for n in corrected]][mask]
    rms = d.pow(2).mean(0).sqrt()
    if corrected:
        rms = torch.where(rms > 0, rms, torch.ones_like(rms) * rms.max().clamp_min(1e-9))
    return HybridSpec(
        corrected=corrected,
        in_states=in_states,
        in_observed=in_observed,
        in_inputs=in_inputs,
        in_parameters=in_params,
        widths=widths,
        activation=str(ude.activation),
        mean=mean.tolist(),
        std=std.tolist(),
        out_scale=(float(ude.output_scale) * rms).tolist(),
        estimated=estimated,
    )


# -- multiple shooting ----------------------------------------------------------------------------
@dataclass
class Shooting:
    """Segments of all training records on a uniform grid of step ``dt`` (s)."""

    dt: float
    steps: int  # grid steps per segment
    exp_index: torch.Tensor  # (S,) batch element of each segment
    first: torch.Tensor  # (S,) True for the first segment of an experiment
    starts: torch.Tensor  # (S,) start time (s)
    x_half: torch.Tensor  # (2*steps+1, S, m) inputs at every half step
    obs_k: torch.Tensor  # (N,) grid interval of each observation
    obs_w: torch.Tensor  # (N,) linear weight within the interval
    obs_s: torch.Tensor  # (N,) segment of each observation
    obs_j: torch.Tensor  # (N,) output index
    obs_y: torch.Tensor  # (N,) measured value
    next_of: torch.Tensor  # (S,) index of the following segment of the same experiment, -1 if last


def plan_shooting(problem: Problem, batch: Batch, cfg: Any) -> Shooting:
    from physmend.ude.timescale import resolved

    cfg = resolved(cfg, problem)
    dt = float(cfg.train.step)
    seg = float(cfg.train.segment_length)
    if not (dt > 0 and seg >= dt):
        raise UDEConfigError(f"train.step and train.segment_length need 0 < step <= segment_length, but got ({dt}, {seg})")
    steps = int(round(seg / dt))
    dtype = batch.t.dtype
    exp_idx, first, starts = [], [], []
    obs: list[tuple[int, int, float, int, float]] = []
    for b, e in enumerate(problem.experiments):
        if e.role != "train":
            continue
        end = float(e.split_time) if e.split_time is not None else float(e.obs_time[-1])
        n_seg = max(1, math.ceil(end / (steps * dt) - 1e-9))
        base = len(starts)
        for k in range(n_seg):
            exp_idx.append(b)
            first.append(k == 0)
            starts.append(k * steps * dt)
        for i, tt in enumerate(e.obs_time):
            if tt >= end and e.split_time is not None:
                break
            s = min(int(tt // (steps * dt)), n_seg - 1)
            local = (tt - starts[base + s]) / dt
            k = min(int(local), steps - 1)
            for j in range(e.obs.shape[1]):
                y = e.obs[i, j]
                if np.isfinite(y):
                    obs.append((base + s, k, local - k, j, float(y)))
    S = len(starts)
    if S == 0:
        raise UDEConfigError("training needs at least one experiment with role 'train'")
    exp_t = torch.tensor(exp_idx)
    start_t = torch.tensor(starts, dtype=dtype)
    grid = start_t[None, :] + torch.arange(2 * steps + 1, dtype=dtype)[:, None] * (dt / 2)  # (2K+1, S)
    x_half = batch.inputs.select(exp_t).at_each(grid)  # (2K+1, S, m): each segment's own inputs
    next_of = torch.full((S,), -1, dtype=torch.long)
    for s in range(S - 1):
        if exp_idx[s + 1] == exp_idx[s] and not first[s + 1]:
            next_of[s] = s + 1
    o = list(zip(*obs))
    return Shooting(
        dt=dt,
        steps=steps,
        exp_index=exp_t,
        first=torch.tensor(first),
        starts=start_t,
        x_half=x_half,
        obs_s=torch.tensor(o[0]),
        obs_k=torch.tensor(o[1]),
        obs_w=torch.tensor(o[2], dtype=dtype),
        obs_j=torch.tensor(o[3]),
        obs_y=torch.tensor(o[4], dtype=dtype),
        next_of=next_of,
    )


def rk4_segments(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], u0: torch.Tensor, plan: Shooting) -> torch.Tensor:
    """Fixed-step RK4 over all segments at once: states at grid points ``(steps+1, S, n)``."""
    h = plan.dt
    u = u0
    out = [u]
    for k in range(plan.steps):
        x0, xm, x1 = plan.x_half[2 * k], plan.x_half[2 * k + 1], plan.x_half[2 * k + 2]
        k1 = rhs(u, x0)
        k2 = rhs(u + 0.5 * h * k1, xm)
        k3 = rhs(u + 0.5 * h * k2, xm)
        k4 = rhs(u + h * k3, x1)
        u = u + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(u)
    return torch.stack(out)


def chained_starts(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], u0: torch.Tensor, plan: Shooting,
                   models: int = 1, keep: Sequence[int] = ()) -> torch.Tensor:
    """Segment starts chained by ``rhs``: every segment after an experiment's first starts where
    ``rhs`` takes the one before it (fixed-step RK4 on the training grid, no gradients), except in
    the state columns ``keep`` (e.g. measured states, which start at their records).

    With ``keep`` empty this is single shooting: no gaps at all. ``u0 (models·S, n)``: starts of
    ``models`` stacked copies of the plan's ``S`` segments, rows model-major (``rhs`` and
    ``plan.x_half`` cover all rows); first segments keep theirs. A model whose chained trajectory
    leaves the finite range keeps its ``u0`` rows. Costs one RK4 pass over all segments per segment
    of the longest experiment.
    """
    S = plan.next_of.shape[0]
    has = plan.next_of >= 0
    if not bool(has.any()):
        return u0.clone()
    offsets = (torch.arange(models) * S)[:, None]
    src = (torch.nonzero(has).flatten()[None] + offsets).flatten()
    dst = (plan.next_of[has][None] + offsets).flatten()
    depth = int(torch.bincount(plan.exp_index).max())
    with torch.no_grad():
        u = u0.clone()
        cols = torch.tensor([i for i in range(u.shape[-1]) if i not in set(keep)], dtype=torch.long)
        for _ in range(depth - 1):
            end = rk4_segments(rhs, u, plan)[-1][src]
            u[dst[:, None], cols[None, :]] = end[:, cols]
        ok = torch.isfinite(u).reshape(models, -1).all(dim=1).repeat_interleave(S)
        return torch.where(ok[:, None], u, u0)


# -- evaluation -------------------------------------------------------------------------------------
def _pooled(err: torch.Tensor, mask: torch.Tensor) -> float:
    e = err[mask]
    e = e[torch.isfinite(e)]
    return float(e.pow(2).mean().sqrt()) if e.numel() else float("nan")


def evaluate(hybrid: HybridModel, problem: Problem, cfg: Any | None = None, *, sim: dict[str, Any] | None = None) -> dict[str, float]:
    """Whole-trajectory metrics of ``hybrid`` on every experiment (single shooting).

    ``val.rmse``: pooled RMSE over validation samples (output units; outputs scaled by their
    training spread when their units differ); ``train.rmse`` likewise on training samples;
    ``rmse.<experiment>.<output>`` per experiment and output (test experiments: report only).
    """
    return _evaluate(hybrid, problem, sim or _sim_opts(cfg))[0]


def metrics_of(problem: Problem, batch: Batch, y: torch.Tensor) -> dict[str, float]:
    """Metrics (see :func:`evaluate`) of whole-trajectory outputs ``y (T, B, k)`` on ``batch``."""
    err = y - batch.obs  # (T, B, k), NaN where not measured
    units = {problem.model.units.get(o, "") for o in problem.model.output_names}
    if len(units) > 1:
        scale = torch.nan_to_num(batch.obs[_train_mask(problem, batch)], nan=0.0).std(0).clamp_min(1e-12)
        scaled = err / scale
    else:
        scaled = err
    tm, vm = _train_mask(problem, batch), _val_mask(problem, batch)
    metrics = {"val.rmse": _pooled(scaled, vm), "train.rmse": _pooled(scaled, tm)}
    test = torch.tensor([e.role == "test" for e in problem.experiments])[None, :].expand_as(tm)
    if bool(test.any()):
        metrics["test.rmse"] = _pooled(scaled, test)
    for b, e in enumerate(problem.experiments):
        for j, out in enumerate(problem.model.output_names):
            col = err[:, b, j]
            col = col[torch.isfinite(col)]
            metrics[f"rmse.{e.id}.{out}"] = float(col.pow(2).mean().sqrt()) if col.numel() else float("nan")
    if not math.isfinite(metrics["val.rmse"]):
        raise TrainingDiverged("validation RMSE is not finite (the hybrid trajectory left the finite range)")
    return metrics


def checkpoint_problem(problem: Problem) -> Problem:
    """``problem`` without its test experiments: all that checkpoints (``val.rmse``, ``train.rmse``)
    need. Test experiments are report-only; simulating them at every checkpoint would cost a
    whole-trajectory solve each for figures nobody reads until the end."""
    keep = [e for e in problem.experiments if e.role != "test"]
    return problem if len(keep) == len(problem.experiments) else dataclasses.replace(problem, experiments=keep)


def _evaluate(hybrid: HybridModel, problem: Problem, sim: dict[str, Any]) -> tuple[dict[str, float], torch.Tensor, Batch]:
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with torch.no_grad():
        p = hybrid.parameters_for(batch.params)
        try:
            states = simulate_with(hybrid.rhs(p), batch, batch.u0, sim)
        except SimulationError as exc:
            raise TrainingDiverged(f"whole-trajectory simulation of the hybrid failed: {exc}") from exc
        y = problem.compiled.outputs(states, batch.inputs.at(batch.t), p[None])
    return metrics_of(problem, batch, y), y, batch


# -- training ----------------------------------------------------------------------------------------
def _initial_segments(problem: Problem, ref: Reference, plan: Shooting) -> torch.Tensor:
    """Segment starts from the model as written, with measured states set to their measurements."""
    t = ref.batch.t
    rows = torch.searchsorted(t, plan.starts).clamp(max=t.shape[0] - 1)
    u = ref.states[rows, plan.exp_index].clone()  # (S, n)
    names = problem.model.state_names
    for j, out in enumerate(problem.model.output_names):
        expr = problem.model.outputs[out]
        if expr.is_Symbol and expr.name in names:
            i = names.index(expr.name)
            obs = ref.batch.obs[:, :, j]
            for s in range(u.shape[0]):
                col = obs[:, plan.exp_index[s]]
                ok = torch.isfinite(col)
                if ok.any():
                    k = int(torch.argmin((t - plan.starts[s]).abs() + (~ok) * 1e30))
                    u[s, i] = col[k]
    return u


def _output_spread(obs: torch.Tensor) -> torch.Tensor:
    """Standard deviation of each output over finite training samples ``obs (N, k)``: ``(k,)``."""
    cols = []
    for c in obs.T:
        c = c[torch.isfinite(c)]
        cols.append(c.std() if c.numel() > 1 else torch.tensor(1.0, dtype=obs.dtype))
    return torch.stack(cols).clamp_min(1e-9)


def _equation_scale(problem: Problem, spec: HybridSpec, params_seg: torch.Tensor, ref: Reference) -> tuple[torch.Tensor, torch.Tensor]:
    """``a_i`` per segment ``(S, k)`` of the corrected equations ``a_i·der(x_i) = …`` and one
    reference size ``()``: the mean RMS of ``a_i·du_i/dt`` along the model-as-written simulation."""
    from physmend.modeling.compile import lambdify_torch

    model = problem.model
    if not spec.corrected:
        return torch.ones(params_seg.shape[0], 0, dtype=params_seg.dtype), torch.ones((), dtype=params_seg.dtype)
    psyms = [v.symbol for v in model.parameters]
    fn = lambdify_torch(psyms, [model.der_coefficient[n] for n in spec.corrected], "der coefficients")

    def coefs(p: torch.Tensor) -> torch.Tensor:
        vals = fn(*p.unbind(-1))
        return torch.stack([torch.as_tensor(v, dtype=p.dtype).expand(p.shape[:-1]) for v in vals], -1)

    idx = [model.state_names.index(n) for n in spec.corrected]
    power = ref.derivs[..., idx] * coefs(ref.batch.params)[None]
    ref_size = power.pow(2).mean(dim=(0, 1)).sqrt().mean().clamp_min(1e-30)
    return coefs(params_seg), ref_size


def _chain(tc: Any) -> bool:
    """``train.segment_starts`` after a warm start: True for ``chained``, False for ``forced``."""
    mode = str(tc.get("segment_starts", "chained"))
    if mode not in ("chained", "forced"):
        raise UDEConfigError(f"train.segment_starts must be 'chained' or 'forced', but got {mode!r}")
    return mode == "chained"


def lr_factor(tc: Any, epochs: int, *, warm: bool) -> Callable[[int], float]:
    """Learning-rate multiplier per epoch: ``train.schedule`` (cosine | none), after a warm start
    ramped up linearly over ``train.warmup_epochs`` so the first steps do not undo it."""
    schedule = str(tc.schedule)
    if schedule not in ("cosine", "none"):
        raise UDEConfigError(f"train.schedule must be 'cosine' or 'none', but got {schedule!r}")
    ramp = max(0, int(tc.get("warmup_epochs", 0))) if warm else 0

    def factor(epoch: int) -> float:
        f = 0.5 * (1 + math.cos(math.pi * min(epoch, epochs) / max(epochs, 1))) if schedule == "cosine" else 1.0
        return f * min(1.0, (epoch + 1) / ramp) if ramp else f

    return factor


def train(cfg: Any, problem: Problem, *, report: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a hybrid model configured by ``cfg.ude`` and ``cfg.train`` on ``problem``.

    ``report(epoch, metrics)`` is called after every evaluation (metrics include ``val.rmse``),
    and at epoch 0 after a derivative-matching warm start (``train.warm_start``);
    an exception it raises (e.g. a pruning signal) stops training and propagates.

    Raises:
        TrainingDiverged: the loss or a trajectory became non-finite.
        UDEConfigError: a ``ude.*`` / ``train.*`` setting does not fit the model.
    """
    from physmend.ude.timescale import check_budget, resolve_times

    torch.manual_seed(int(cfg.get("seed", 0)))
    ref = reference(problem, cfg)
    cfg = resolve_times(cfg, problem, ref)  # 'auto' time settings from the data and the model
    tc = cfg.train
    spec = build_spec(cfg, problem, ref)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    plan = plan_shooting(problem, ref.batch, cfg)
    check_budget(plan, problem, [cfg])
    seg0 = _initial_segments(problem, ref, plan)
    forced = warm_start(hybrid, problem, ref.batch, cfg)
    if forced is not None:
        seg0 = segment_starts(forced, plan.exp_index, plan.starts, seg0)
    fixed_first = ref.batch.u0[plan.exp_index]
    params_seg = ref.batch.params[plan.exp_index]
    if _chain(tc) and forced is not None:
        seg0 = chained_starts(hybrid.rhs(hybrid.parameters_for(params_seg)), torch.where(plan.first[:, None], fixed_first, seg0), plan,
                              keep=forced.measured)
    state_scale = ref.states[_train_mask(problem, ref.batch)].std(0).clamp_min(1e-3)
    # segment starts are trained as offsets in units of each state's spread (Adam steps are ~lr)
    free = torch.nn.Parameter(torch.zeros_like(seg0))
    out_std = _output_spread(ref.batch.obs[_train_mask(problem, ref.batch)])
    groups = [{"params": list(hybrid.net.parameters()), "weight_decay": float(tc.weight_decay)},
              {"params": [free], "weight_decay": 0.0}]
    if spec.estimated:
        groups.append({"params": [hybrid.est_raw], "weight_decay": 0.0})
    opt = torch.optim.AdamW(groups, lr=float(tc.lr))
    epochs = int(tc.epochs)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor(tc, epochs, warm=forced is not None))
    sim = _sim_opts(cfg)
    eval_every = max(1, int(tc.eval_every))
    patience = int(tc.patience)
    cont_w = float(tc.continuity_weight)
    sparsity = float(tc.get("sparsity", 0.0))
    eq_coef, eq_ref = _equation_scale(problem, spec, params_seg, ref)
    history: list[dict[str, float]] = []
    best: tuple[float, dict[str, Any], dict[str, float]] | None = None
    since_best = 0
    has_next = plan.next_of >= 0
    outputs = problem.compiled.outputs
    checked = checkpoint_problem(problem)

    def checkpoint(epoch: int, loss: float, fit: float) -> bool:
        """Evaluate whole trajectories, keep the best state; True when patience has run out."""
        nonlocal best, since_best
        metrics, _, _ = _evaluate(hybrid, checked, sim)
        row = {"epoch": float(epoch), "loss": loss, "fit_loss": fit,
               **{k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")}}
        history.append(row)
        if best is None or metrics["val.rmse"] < best[0]:
            best = (metrics["val.rmse"], copy.deepcopy(hybrid.state_dict()), metrics)
            since_best = 0
        else:
            since_best += 1
        if report is not None:
            report(epoch, row)
        return patience > 0 and since_best >= patience

    if forced is not None:  # the warm start itself is a candidate (it may already be the best fit)
        checkpoint(0, float("nan"), float("nan"))
    for epoch in range(1, epochs + 1):
        opt.zero_grad(set_to_none=True)
        p = hybrid.parameters_for(params_seg)
        u0 = torch.where(plan.first[:, None], fixed_first, seg0 + free * state_scale)
        traj = rk4_segments(hybrid.rhs(p), u0, plan)  # (K+1, S, n)
        y_grid = outputs(traj, plan.x_half[0::2], p[None])  # (K+1, S, k)
        ya = y_grid[plan.obs_k, plan.obs_s, plan.obs_j]
        yb = y_grid[plan.obs_k + 1, plan.obs_s, plan.obs_j]
        pred = ya + plan.obs_w * (yb - ya)
        fit = (((pred - plan.obs_y) / out_std[plan.obs_j]) ** 2).mean()
        loss = fit
        if bool(has_next.any()):
            gap = (traj[-1][has_next] - u0[plan.next_of[has_next]]) / state_scale
            loss = loss + cont_w * gap.pow(2).mean()
        if sparsity > 0 and spec.corrected:
            # group lasso in the equations' own units (a_i·correction_i: W for heat balances),
            # relative to the typical size of those terms: few, direct corrections are cheapest
            corr = hybrid.corrections(traj, plan.x_half[0::2], p) * eq_coef  # (K+1, S, k)
            loss = loss + sparsity * (corr.pow(2).mean(dim=(0, 1)).add(1e-30).sqrt() / eq_ref).sum()
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"training loss became non-finite at epoch {epoch} (lr {float(tc.lr):g}); "
                                   "try a smaller train.lr or train.step")
        loss.backward()
        torch.nn.utils.clip_grad_norm_(hybrid.parameters(), 10.0)
        opt.step()
        sched.step()
        if (epoch % eval_every == 0 or epoch == epochs) and checkpoint(epoch, float(loss.detach()), float(fit.detach())):
            break
    assert best is not None
    hybrid.load_state_dict(best[1])
    metrics, y, batch = _evaluate(hybrid, problem, sim)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref),
        hybrid=hybrid,
    )


# -- artifacts -------------------------------------------------------------------------------------
def artifacts_of(hybrid: HybridModel, metrics: dict[str, float]) -> dict[str, str | bytes]:
    """Plain files: ``model/weights.pt`` (a state_dict of tensors) and ``model/hybrid.json``."""
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu() for k, v in hybrid.state_dict().items()}, buf)
    meta = {"spec": hybrid.spec.to_dict(), "estimates": hybrid.estimates(), "metrics": metrics, "format": 1}
    return {"model/weights.pt": buf.getvalue(), "model/hybrid.json": json.dumps(meta, indent=2)}


def fit_figures(problem: Problem, batch: Batch, y: torch.Tensor, ref: Reference) -> dict[str, Any]:
    """Measured vs model-as-written vs hybrid outputs, one figure per experiment."""
    from physmend.explain.plots import fit_figure

    t = batch.t.numpy() / 3600
    y_ref = problem.compiled.outputs(ref.states, ref.inputs, ref.batch.params[None]).numpy()
    figs: dict[str, Any] = {}
    for b, e in enumerate(problem.experiments):
        curves = [("model as written", y_ref[:, b], {"ls": "--", "color": "C3", "lw": 1}),
                  ("hybrid (UDE)", y[:, b].numpy(), {"color": "C0", "lw": 1.2})]
        split = float(e.split_time) / 3600 if e.split_time is not None else None
        figs[f"plots/fit_{e.id}.png"] = fit_figure(t, batch.obs[:, b].numpy(), curves, problem.model.output_names,
                                                   problem.model.units, f"experiment {e.id} ({e.role})", split)
    return figs
