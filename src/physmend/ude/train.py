"""Training a hybrid model: multiple shooting on the training records, honest evaluation.

Training solves every segment of every training experiment in one batched fixed-step RK4
solve (segment starts are trainable, a continuity penalty joins them; the first segment of each
experiment starts from its known initial state). Every reported metric comes from simulating
whole trajectories (single shooting, adaptive stiff solver) — never from the segments.

Validation: validation experiments if the data config has any, otherwise the carved last part of
each training record (``split_time``); training never sees those samples.

Only :func:`train` lives here; its pieces are modules of their own, which this one imports:
``reference``, ``spec``, ``shooting``, ``warmstart``, ``schedule``, ``metrics``, ``outcome``,
``artifacts`` (and ``timescale``); within ``physmend.ude`` only the package's face imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any
import copy
import math

import torch

from physmend.device import placed
from physmend.problem import Problem
from physmend.ude.artifacts import artifacts_of, fit_figures
from physmend.ude.drive import drivable, hybrid_drive
from physmend.ude.hybrid import HybridModel
from physmend.ude.metrics import _evaluate, checkpoint_problem
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.polish import fit_at, polish_iterations, polish_lbfgs, worth_polishing
from physmend.ude.reference import _sim_opts, train_mask, reference
from physmend.ude.schedule import _chain, cycle_of, fit_gain, fit_progressed, lr_factor, restarts, stops_at
from physmend.ude.shooting import _equation_scale, initial_segments, output_spread, chained_starts, noise_fit, plan_shooting, rk4_segments
from physmend.ude.spec import build_spec
from physmend.ude.warmstart import segment_starts, warm_start

# not used here, still importable from here (the import paths from before the split)
from physmend.ude.hybrid import UDEConfigError  # noqa: F401
from physmend.ude.metrics import evaluate, metrics_of  # noqa: F401
from physmend.ude.reference import Reference, simulate_with  # noqa: F401
from physmend.ude.shooting import BOX_MARGIN, Shooting, pinned_starts, segments_finite  # noqa: F401
from physmend.ude.spec import informative_parameters  # noqa: F401


def train(cfg: Any, problem: Problem, *, report: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a hybrid model configured by ``cfg.ude`` and ``cfg.train`` on ``problem``.

    ``report(epoch, metrics)`` is called after every evaluation (metrics include ``val.rmse``),
    and at epoch 0 after a derivative-matching warm start (``train.warm_start``);
    an exception it raises (e.g. a pruning signal) stops training and propagates.

    Runs on ``problem.device`` (:mod:`physmend.device`); the result's model is on the CPU.

    Raises:
        TrainingDiverged: the loss or a trajectory became non-finite.
        UDEConfigError: a ``ude.*`` / ``train.*`` setting does not fit the model.
    """
    with placed(problem.device):
        result = _train(cfg, problem, report)
    return result.on_cpu()


def _train(cfg: Any, problem: Problem, report: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    """:func:`train` on the current default device."""
    from physmend.ude.timescale import check_budget, resolve_times

    torch.manual_seed(int(cfg.get("seed", 0)))
    ref = reference(problem, cfg, bounded=True)
    cfg = resolve_times(cfg, problem, ref)  # 'auto' time settings from the data and the model
    tc = cfg.train
    spec = build_spec(cfg, problem, ref)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    plan = plan_shooting(problem, ref.batch, cfg)
    check_budget(plan, problem, [cfg])
    seg0 = initial_segments(problem, ref, plan)
    initial = copy.deepcopy(hybrid.state_dict())
    forced = warm_start(hybrid, problem, ref.batch, cfg)
    if forced is not None:
        seg0 = segment_starts(forced, plan.exp_index, plan.starts, seg0)
    fixed_first = ref.batch.u0[plan.exp_index]
    pinned, lo, hi = pinned_starts(ref.batch, plan, problem.compiled.state_names)
    params_seg = ref.batch.params[plan.exp_index]
    box = hybrid.spec.box(BOX_MARGIN, problem.dtype)
    # judged as training takes the segments: states held in the box (a warm start that sends one
    # segment of many below zero, where the model as written explodes, is still a start)
    if forced is not None and not segments_finite(hybrid.rhs(hybrid.parameters_for(params_seg)),
                                                  torch.where(pinned, fixed_first, seg0), plan, box):
        hybrid.load_state_dict(initial)  # the warm-started network leaves the finite range: not a start
        forced = None
    if _chain(tc) and forced is not None:
        seg0 = chained_starts(hybrid.rhs(hybrid.parameters_for(params_seg)), torch.where(plan.first[:, None], fixed_first, seg0), plan,
                              keep=forced.measured)
    state_scale = ref.states[train_mask(problem, ref.batch)].std(0).clamp_min(1e-3)
    # segment starts are trained as offsets in units of each state's spread (Adam steps are ~lr)
    free = torch.nn.Parameter(torch.zeros_like(seg0))
    out_std = output_spread(ref.batch.obs[train_mask(problem, ref.batch)])
    groups = [{"params": list(hybrid.net.parameters()), "weight_decay": float(tc.weight_decay)},
              {"params": [free], "weight_decay": 0.0}]
    if spec.estimated:
        groups.append({"params": [hybrid.est_raw], "weight_decay": 0.0})
    opt = torch.optim.AdamW(groups, lr=float(tc.lr))
    epochs = int(tc.epochs)
    cycles = 1 + restarts(tc)
    factor = lr_factor(tc, epochs, warm=forced is not None)
    # a cycle that ends with no checkpoint that could be simulated restarts the schedule (see restarts())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: factor(e % epochs))
    sim = _sim_opts(cfg)
    eval_every = max(1, int(tc.eval_every))
    patience = int(tc.patience)
    polish = polish_iterations(tc)
    cont_w = float(tc.continuity_weight)
    sparsity = float(tc.get("sparsity", 0.0))
    eq_coef, eq_ref = _equation_scale(problem, spec, params_seg, ref)
    history: list[dict[str, float]] = []
    best: tuple[float, dict[str, Any], dict[str, float]] | None = None
    since_best = 0
    gain = fit_gain(tc)
    best_fit: float | None = None  # the best whole-trajectory training RMSE so far (train.patience_fit_gain)
    good_cycle: int | None = None  # the cycle of the first checkpoint that could be simulated
    failed: TrainingDiverged | None = None  # the last checkpoint whose whole trajectory failed
    has_next = plan.next_of >= 0
    outputs = problem.compiled.outputs
    checked = checkpoint_problem(problem)

    def checkpoint(epoch: int, loss: float, fit: float) -> bool:
        """Evaluate whole trajectories, keep the best state; True when patience has run out."""
        nonlocal best, since_best, failed, good_cycle, best_fit
        try:
            metrics, _, _ = _evaluate(hybrid, checked, sim)
        except TrainingDiverged as exc:  # not a candidate; training goes on, patience counts it
            failed = exc
            history.append({"epoch": float(epoch), "loss": loss, "fit_loss": fit, "val.rmse": math.inf,
                            "train.rmse": math.inf})
            since_best += 1
            # patience runs out only after a good checkpoint: a diverging start is for training to repair
            return patience > 0 and best is not None and since_best >= patience
        row = {"epoch": float(epoch), "loss": loss, "fit_loss": fit,
               **{k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")}}
        history.append(row)
        if best is None:
            good_cycle = cycle_of(epoch, epochs)
        fitting, best_fit = fit_progressed(metrics["train.rmse"], best_fit, gain)
        if best is None or metrics["val.rmse"] < best[0]:
            best = (metrics["val.rmse"], copy.deepcopy(hybrid.state_dict()), metrics)
            since_best = 0
        elif fitting:
            since_best = 0
        else:
            since_best += 1
        if report is not None:
            report(epoch, row)
        return patience > 0 and since_best >= patience

    fast = drivable(hybrid)
    shared = fast and problem.compiled.shares_matrices(int(torch.unique(plan.exp_index).numel()))

    def objective() -> tuple[torch.Tensor, torch.Tensor]:
        """The multiple-shooting loss of the current network, segment starts and estimates."""
        if shared:  # one physics matrix per experiment (BoundRhs), not one per segment
            p_exp = hybrid.parameters_for(ref.batch.params)
            p = p_exp[plan.exp_index]
        else:
            p = hybrid.parameters_for(params_seg)
        u0 = torch.where(pinned, fixed_first, torch.clamp(seg0 + free * state_scale, lo, hi))
        if fast:  # the same function with fewer operations per evaluation (physmend.ude.drive)
            rhs, drives = (hybrid_drive(hybrid, p_exp, plan.x_half, plan.exp_index) if shared
                           else hybrid_drive(hybrid, p, plan.x_half))
            traj = rk4_segments(rhs, u0, plan, box, drives)  # (K+1, S, n)
        else:
            traj = rk4_segments(hybrid.rhs(p), u0, plan, box)
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
        return loss, fit

    if forced is not None:  # the warm start itself is a candidate (it may already be the best fit)
        checkpoint(0, float("nan"), float("nan"))
    epoch = 0
    for epoch in range(1, epochs * cycles + 1):
        if stops_at(epoch, epochs, good_cycle):
            epoch -= 1
            break  # a cycle ended after the model had been good long enough: no restart
        opt.zero_grad(set_to_none=True)
        loss, fit = objective()
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"training loss became non-finite at epoch {epoch} (lr {float(tc.lr):g}); "
                                   "try a smaller train.lr or train.step")
        loss.backward()
        torch.nn.utils.clip_grad_norm_(hybrid.parameters(), 10.0)
        opt.step()
        sched.step()
        if (epoch % eval_every == 0 or epoch % epochs == 0) and checkpoint(epoch, float(loss.detach()), float(fit.detach())):
            break
    if best is not None and polish > 0 and worth_polishing(fit_at(history, best[0]),
                                                           noise_fit(ref.batch, train_mask(problem, ref.batch), out_std)):
        hybrid.load_state_dict(best[1])
        since_best = 0
        polish_lbfgs(objective, [*hybrid.net.parameters(), free, *([hybrid.est_raw] if spec.estimated else [])],
                     polish, eval_every, lambda k, loss, fit: checkpoint(epoch + k, float(loss), float(fit)))
    if best is None:  # every checkpoint failed
        raise failed or TrainingDiverged("no checkpoint was evaluated")
    hybrid.load_state_dict(best[1])
    metrics, y, batch = _evaluate(hybrid, problem, sim)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    metrics["checkpoints.failed"] = float(sum(math.isinf(r["val.rmse"]) for r in history))
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref),
        hybrid=hybrid,
    )

