"""Training a hybrid model: multiple shooting on the training records, honest evaluation.

Training solves every segment of every training experiment in one batched fixed-step RK4
solve (segment starts are trainable, a continuity penalty joins them; the first segment of each
experiment starts from its known initial state). Every reported metric comes from simulating
whole trajectories (single shooting, adaptive stiff solver) — never from the segments.

Validation: validation experiments if the data config has any, otherwise the carved last part of
each training record (``split_time``); training never sees those samples.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any
import copy
import io
import json
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch
from physmend.ude.hybrid import HybridModel, UDEConfigError
# names below that train() does not use stay importable from here (older import paths): the
# training pieces live in reference, spec, shooting, metrics and outcome
from physmend.ude.metrics import _evaluate, checkpoint_problem, evaluate, metrics_of
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.reference import Reference, _sim_opts, _train_mask, reference, simulate_with
from physmend.ude.shooting import Shooting, _equation_scale, _initial_segments, _output_spread, chained_starts, plan_shooting, rk4_segments
from physmend.ude.spec import build_spec, informative_parameters
from physmend.ude.warmstart import segment_starts, warm_start


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
