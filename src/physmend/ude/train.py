"""Training a hybrid model: multiple shooting on the training records, honest evaluation.

Training solves every segment of every training experiment in one batched fixed-step RK4
solve (segment starts are trainable, a continuity penalty joins them; the first segment of each
experiment starts from its known initial state). Every reported metric comes from simulating
whole trajectories (single shooting, adaptive stiff solver) — never from the segments.

Validation: validation experiments if the data config has any, otherwise the carved last part of
each training record (``split_time``); training never sees those samples.

Only :func:`train` lives here; its pieces are modules of their own. The rules of checkpoints,
patience, restarts and polishing are shared with the stacked trainer (:mod:`physmend.ude.checkpoints`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any
import copy

import torch

from physmend.device import placed
from physmend.problem import Problem
from physmend.settings import training_settings
from physmend.ude.artifacts import artifacts_of, fit_figures
from physmend.ude.checkpoints import Checkpoints, evaluation_due, last_epoch
from physmend.ude.adjoint import adjoint_applies, hybrid_solve
from physmend.ude.drive import drivable, hybrid_drive
from physmend.ude.hybrid import HybridModel
from physmend.ude.metrics import checkpoint_problem, evaluate_with
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.polish import polish_lbfgs
from physmend.ude.reference import reference, train_mask
from physmend.ude.schedule import lr_factor
from physmend.ude.shooting import (BOX_MARGIN, chained_starts, equation_scale, initial_segments, noise_fit,
                                   output_spread, pinned_starts, plan_shooting, rk4_segments, segments_finite)
from physmend.ude.spec import build_spec
from physmend.ude.warmstart import segment_starts, warm_start


def train(cfg: Any, problem: Problem, *, report: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a hybrid model configured by ``cfg.ude`` and ``cfg.train`` on ``problem``.

    ``cfg``: a composed configuration, one built in code (a missing key takes its shipped default),
    or its :class:`~physmend.settings.TrainingSettings`; its settings are built and checked once.

    ``report(epoch, metrics)`` is called after every evaluation (metrics include ``val.rmse``),
    and at epoch 0 after a derivative-matching warm start (``train.warm_start``);
    an exception it raises (e.g. a pruning signal) stops training and propagates.

    Runs on ``problem.device`` (:mod:`physmend.device`); the result's model is on the CPU.

    Raises:
        TrainingDiverged: the loss or a trajectory became non-finite.
        UDEConfigError: a ``ude.*`` / ``train.*`` setting does not fit the model.
        SettingError: a setting breaks its rule (kind, range, choices).
    """
    settings = training_settings(cfg)
    with placed(problem.device):
        result = _train(settings, problem, report)
    return result.on_cpu()


def _train(settings: Any, problem: Problem, report: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    """:func:`train` on the current default device, from checked settings."""
    from physmend.ude.timescale import check_budget, resolve_settings

    torch.manual_seed(settings.seed)
    ref = reference(problem, settings, bounded=True)
    cfg = resolve_settings(settings, problem, ref)  # 'auto' time settings from the data and the model, once
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
    if tc.chained and forced is not None:
        seg0 = chained_starts(hybrid.rhs(hybrid.parameters_for(params_seg)), torch.where(plan.first[:, None], fixed_first, seg0), plan,
                              keep=forced.measured)
    mask = train_mask(problem, ref.batch)
    state_scale = ref.states[mask].std(0).clamp_min(1e-3)
    # segment starts are trained as offsets in units of each state's spread (Adam steps are ~lr)
    free = torch.nn.Parameter(torch.zeros_like(seg0))
    out_std = output_spread(ref.batch.obs[mask])
    groups = [{"params": list(hybrid.net.parameters()), "weight_decay": float(tc.weight_decay)},
              {"params": [free], "weight_decay": 0.0}]
    if spec.estimated:
        groups.append({"params": [hybrid.est_raw], "weight_decay": 0.0})
    opt = torch.optim.AdamW(groups, lr=float(tc.lr))
    epochs = tc.epochs
    factor = lr_factor(tc, epochs, warm=forced is not None)
    # a cycle that ends with no checkpoint that could be simulated restarts the schedule (Checkpoints.stops_before)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda e: factor(e % epochs))
    sim = cfg.simulate.solver()
    eq_coef, eq_ref = equation_scale(problem, spec, params_seg, ref)
    has_next = plan.next_of >= 0
    outputs = problem.compiled.outputs
    checked = checkpoint_problem(problem)
    marks = Checkpoints(tc)

    def checkpoint(epoch: int, loss: float, fit: float) -> bool:
        """Evaluate whole trajectories, keep the best state; True when patience has run out."""
        try:
            metrics, _, _ = evaluate_with(hybrid, checked, sim)
        except TrainingDiverged as exc:  # not a candidate; training goes on, patience counts it
            return marks.diverged(epoch, loss, fit, exc)
        row = marks.record(epoch, loss, fit, metrics, lambda: copy.deepcopy(hybrid.state_dict()))
        if report is not None:
            report(epoch, row)
        return marks.patience_ran_out

    fast = drivable(hybrid)
    shared = fast and problem.compiled.shares_matrices(int(torch.unique(plan.exp_index).numel()))
    adjoint = tc.backward == "adjoint" and adjoint_applies(hybrid)

    def objective() -> tuple[torch.Tensor, torch.Tensor]:
        """The multiple-shooting loss of the current network, segment starts and estimates."""
        if shared:  # one physics matrix per experiment (BoundRhs), not one per segment
            p_exp = hybrid.parameters_for(ref.batch.params)
            p = p_exp[plan.exp_index]
        else:
            p = hybrid.parameters_for(params_seg)
        u0 = torch.where(pinned, fixed_first, torch.clamp(seg0 + free * state_scale, lo, hi))
        if adjoint:  # the same solve, its backward pass written by hand (physmend.ude.adjoint)
            traj = hybrid_solve(hybrid, p_exp, u0, plan, box, plan.exp_index) if shared else hybrid_solve(hybrid, p, u0, plan, box)
        elif fast:  # the same function with fewer operations per evaluation (physmend.ude.drive)
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
            loss = loss + tc.continuity_weight * gap.pow(2).mean()
        if tc.sparsity > 0 and spec.corrected:
            # group lasso in the equations' own units (a_i·correction_i: W for heat balances),
            # relative to the typical size of those terms: few, direct corrections are cheapest
            corr = hybrid.corrections(traj, plan.x_half[0::2], p) * eq_coef  # (K+1, S, k)
            loss = loss + tc.sparsity * (corr.pow(2).mean(dim=(0, 1)).add(1e-30).sqrt() / eq_ref).sum()
        return loss, fit

    if forced is not None:  # the warm start itself is a candidate (it may already be the best fit)
        checkpoint(0, float("nan"), float("nan"))
    epoch = 0
    for epoch in range(1, epochs * tc.cycles + 1):
        if marks.stops_before(epoch):
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
        if evaluation_due(epoch, tc) and checkpoint(epoch, float(loss.detach()), float(fit.detach())):
            break
    if marks.worth_polishing(noise_fit(ref.batch, mask, out_std)):
        last = last_epoch([marks.history], epoch)
        hybrid.load_state_dict(marks.best_state())
        marks.since_best = 0
        polish_lbfgs(objective, [*hybrid.net.parameters(), free, *([hybrid.est_raw] if spec.estimated else [])],
                     tc.polish_iterations, tc.eval_every, lambda k, loss, fit: checkpoint(last + k, float(loss), float(fit)))
    hybrid.load_state_dict(marks.best_state())  # every checkpoint failed: the last failure is raised
    metrics, y, batch = evaluate_with(hybrid, problem, sim)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    metrics["checkpoints.failed"] = marks.failures
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=marks.history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref),
        hybrid=hybrid,
    )
