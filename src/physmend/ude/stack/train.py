"""The stack's training: :func:`train_stack` (settings built and times resolved once, models
prepared, the batched warm start), the shared epoch loop over the active models, polishing, and the
final evaluations. Each model's checkpoints follow the rules of :mod:`physmend.ude.checkpoints`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any
import copy
import json

import torch

from physmend.device import placed
from physmend.problem import Problem
from physmend.settings import TrainingSettings, training_settings
from physmend.simulate import make_batch
from physmend.ude.artifacts import artifacts_of, fit_figures
from physmend.ude.checkpoints import evaluation_due, last_epoch
from physmend.ude.hybrid import UDEConfigError
from physmend.ude.metrics import evaluate_with
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.polish import polish_lbfgs
from physmend.ude.reference import Reference, train_mask
from physmend.ude.shooting import Shooting, noise_fit, output_spread
from physmend.ude.stack.keys import check_shared
from physmend.ude.stack.members import (check_same_shape, drop_unstable_warm_starts, prepare, shared_warm_start,
                                        warm_fit_members, warm_settings)
from physmend.ude.stack.plan import setup
from physmend.ude.stack.solve import Member, Stack
from physmend.ude.warmstart import Forced, recall_derived, remember_derived, same_warm_start

#: ``report(i, epoch, row)`` after every evaluation of model ``i``
Report = Callable[[int, int, dict[str, float]], None]


def train_stack(cfgs: Sequence[Any], problem: Problem, *, report: Report | None = None,
                final_eval: str = "own", figures: bool = True) -> list[TrainResult | BaseException]:
    """Train one hybrid model per configuration, all in one batched solve (see module docstring).

    Args:
        cfgs: one full configuration per model. They may differ in ``seed``, ``ude.width``,
            ``ude.depth``, ``ude.activation``, ``ude.output_scale``, ``train.lr``,
            ``train.weight_decay``, ``train.sparsity`` and the warm-start settings; everything in
            :data:`SHARED_KEYS` must agree (see :func:`stack_key`). Models with the same warm-start
            settings are warm-started together, as one batched regression.
        problem: the problem every model is trained on.
        report: ``report(i, epoch, row)`` after every evaluation of model ``i`` (``row`` as the
            ``report`` of :func:`physmend.ude.train.train` gets it). An exception it raises stops
            model ``i`` only and becomes its result.
        final_eval: ``"own"``: each model's final metrics come from its own solo evaluation, exactly as
            ``train()`` computes them (a reloaded model reproduces them); costs one solo solve per
            model. ``"batched"``: the best checkpoints of all finished models are simulated on every
            experiment in one batched solve (the adaptive solver takes the steps the most demanding
            model needs, so each agrees with its solo evaluation to the solver tolerance).
        figures: attach the fit figures (one per experiment) to each result.

    A stack whose training plan would need more memory than ``train.memory_limit_gib`` is trained
    as consecutive stacks that fit (:func:`~physmend.ude.timescale.budget_parts`), one after
    another; a model that alone needs more is refused (its result is the
    :class:`~physmend.ude.timescale.TimeSettingError`).

    Returns:
        One entry per configuration, in order: the model's :class:`TrainResult` (as
        :func:`physmend.ude.train.train` would return it), or the exception that stopped it —
        :class:`TrainingDiverged` when its loss or trajectory became non-finite, the exception
        raised by ``report``, or an error of its own settings.

    Raises:
        UDEConfigError: the configurations differ in a shared setting (the message names the key).
    """
    if final_eval not in ("own", "batched"):
        raise UDEConfigError(f"final_eval must be 'own' or 'batched', but got {final_eval!r}")
    if not cfgs:
        return []
    check_shared(cfgs)  # before the problem is used
    with placed(problem.device):  # physmend.device; every result's model comes back on the CPU
        results = _train_stack(cfgs, problem, report, final_eval, figures)
    return [r.on_cpu() if isinstance(r, TrainResult) else r for r in results]


def _train_stack(cfgs: Sequence[Any], problem: Problem, report: Report | None, final_eval: str,
                 figures: bool) -> list[TrainResult | BaseException]:
    """:func:`train_stack` on the current default device."""
    from physmend.ude.timescale import budget_parts, check_budget, resolve_settings

    settings = [training_settings(cfg) for cfg in cfgs]  # built and checked once
    ref, _ = setup(problem, settings[0], plan=False)
    settings = [resolve_settings(s, problem, ref) for s in settings]  # 'auto' time settings, as train() resolves them
    cfg0 = settings[0]
    ref, plan = setup(problem, cfg0)
    parts = budget_parts(plan, problem, settings)
    if len(parts) > 1:  # more models than train.memory_limit_gib allows at once: stacks that fit, one after another
        return _in_parts(parts, cfgs, problem, report, final_eval, figures)
    check_budget(plan, problem, settings)
    results: list[TrainResult | BaseException | None] = [None] * len(settings)
    members: list[Member] = []
    warm_kinds = {warm_settings(s) for s in settings}
    batched_warm = len(warm_kinds) == 1 and next(iter(warm_kinds))[0] == "auto"
    for i, s in enumerate(settings):
        try:
            members.append(prepare(s, problem, ref, plan, i, warm=not batched_warm))
        except Exception as exc:  # noqa: BLE001 - train(cfg) would have raised it: this trial's outcome
            results[i] = exc
    if members:
        check_same_shape(members)
        warm = shared_warm_start(members, problem, ref, plan) if batched_warm else None
        finished = _run(members, problem, ref, plan, cfg0, report, warm)
        sim = cfg0.simulate.solver()
        done = [mem for mem in finished if mem.outcome is None]
        final = _final_batched(done, problem, ref, plan, cfg0, sim) if final_eval == "batched" and done else {}
        for mem in finished:
            results[mem.slot] = mem.outcome if mem.outcome is not None else _result(mem, problem, ref, sim, final.get(mem.slot), figures)
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def _in_parts(parts: list[list[int]], cfgs: Sequence[Any], problem: Problem, report: Report | None, final_eval: str,
              figures: bool) -> list[TrainResult | BaseException]:
    """:func:`_train_stack` of each part of ``cfgs`` (positions, :func:`~physmend.ude.timescale.budget_parts`)
    in turn, results in the order of ``cfgs``; a model that alone needs more memory than the limit
    gets the refusal as its result."""
    from physmend.ude.timescale import TimeSettingError

    results: list[TrainResult | BaseException | None] = [None] * len(cfgs)
    for part in parts:
        sub = None if report is None else (lambda j, epoch, row, part=part: report(part[j], epoch, row))
        try:
            got: list[TrainResult | BaseException] = _train_stack([cfgs[i] for i in part], problem, sub, final_eval, figures)
        except TimeSettingError as exc:  # the part is one model over the limit alone (parts of more fit)
            got = [exc] * len(part)
        for i, result in zip(part, got):
            results[i] = result
    return results  # type: ignore[return-value]


def _run(members: list[Member], problem: Problem, ref: Reference, plan: Shooting, cfg: TrainingSettings,
         report: Report | None, warm: tuple[Forced, int, int] | None = None) -> list[Member]:
    """The shared epoch loop (after the batched warm start ``warm``: forced trajectories, iterations,
    window); returns every member, each with a best checkpoint or an outcome."""
    tc = cfg.train
    if warm is not None:
        initial = [copy.deepcopy(mem.hybrid.state_dict()) for mem in members]
        warm_fit_members(members, problem, ref, plan, cfg, *warm)
        drop_unstable_warm_starts(members, initial, ref, plan)
    stack = Stack(members, problem, ref, plan, cfg)
    if warm is not None:
        stack.chain_starts()
    sim = cfg.simulate.solver()
    checked_name = ("checkpoint", json.dumps(sim, sort_keys=True, default=str), id(problem))
    epochs = tc.epochs

    def checkpoint(positions: list[int], epoch: int, loss: torch.Tensor | None, fit: torch.Tensor | None,
                   known: dict[int, dict[str, float]] | None = None, as_warm_started: bool = False) -> None:
        """Evaluate the models at ``positions`` (``known``: metrics of some already, by position); mark
        those whose patience ran out or that failed as done. ``as_warm_started``: no model has trained
        yet, so models of one warm start (trials that differ in training settings only) are one model."""
        known = known or {}
        todo = [pos for pos in positions if pos not in known]
        outcomes: dict[int, tuple[dict[str, float], Any] | BaseException] = {pos: (known[pos], None) for pos in positions if pos in known}
        if todo:
            firsts = same_warm_start([stack.members[pos].warm_key if as_warm_started else None for pos in todo])
            first = {pos: todo[j] for pos, j in zip(todo, firsts)}  # position -> the position evaluated for it
            solved = sorted(set(first.values()))
            evaluated = dict(zip(solved, stack.evaluate(solved, sim)))
            outcomes.update({pos: evaluated[first[pos]] for pos in todo})
        for pos in positions:
            outcome = outcomes[pos]
            mem = stack.members[pos]
            loss_p = float("nan") if loss is None else float(loss[pos])
            fit_p = float("nan") if fit is None else float(fit[pos])
            if isinstance(outcome, TrainingDiverged):  # not a candidate; training goes on, patience counts it
                mem.done = mem.marks.diverged(epoch, loss_p, fit_p, outcome)
                continue
            if isinstance(outcome, BaseException):
                mem.outcome, mem.done = outcome, True
                continue
            metrics, _ = outcome
            if epoch == 0 and pos not in known and mem.warm_key is not None:
                remember_derived(mem.warm_key, checked_name, (problem, dict(metrics)))

            def state(pos: int = pos, mem: Member = mem) -> dict[str, Any]:
                stack.write_back(pos)
                return copy.deepcopy(mem.hybrid.state_dict())

            row = mem.marks.record(epoch, loss_p, fit_p, metrics, state)
            if report is not None:
                try:
                    report(mem.slot, epoch, row)
                except Exception as exc:  # noqa: BLE001 - e.g. a pruning signal: this model stops
                    mem.outcome, mem.done = exc, True
                    continue
            if mem.marks.patience_ran_out:
                mem.done = True

    def drop_done() -> None:
        stack.keep([i for i, mem in enumerate(stack.members) if not mem.done])

    warm_started = [i for i, mem in enumerate(stack.members) if mem.forced is not None]
    if warm_started:  # a warm start itself is a candidate (it may already be the best fit), as in train()
        # its evaluation follows from the warm start alone: an earlier stack of this process may have it
        known = {}
        for pos in warm_started:
            key = stack.members[pos].warm_key
            stored = None if key is None else recall_derived(key, checked_name)
            if stored is not None and stored[0] is problem:
                known[pos] = dict(stored[1])
        checkpoint(warm_started, 0, None, None, known, as_warm_started=True)
        drop_done()
    epoch = 0
    for epoch in range(1, epochs * tc.cycles + 1):
        for mem in stack.members:  # a cycle ended: the models that need it go on, their schedule restarted
            mem.done = mem.done or mem.marks.stops_before(epoch)
        drop_done()
        if not stack.members:
            break
        loss, fit = stack.losses()
        ok = torch.isfinite(loss.detach())
        for pos in torch.nonzero(~ok).flatten().tolist():
            mem = stack.members[pos]
            mem.outcome = TrainingDiverged(f"training loss became non-finite at epoch {epoch} (lr {float(mem.cfg.train.lr):g}); "
                                           "try a smaller train.lr or train.step")
            mem.done = True
        if bool(ok.any()):
            lr = torch.tensor([mem.lrs[(epoch - 1) % epochs] for mem in stack.members], dtype=stack.dtype)
            stack.step(loss, lr, torch.nonzero(ok).flatten())
        loss, fit = loss.detach(), fit.detach()
        if evaluation_due(epoch, tc):
            live = [i for i, mem in enumerate(stack.members) if not mem.done]
            if live:
                checkpoint(live, epoch, loss, fit)
        drop_done()
    last = last_epoch([mem.marks.history for mem in members], epoch)  # the last checkpoint
    ready = [mem for mem in members if mem.outcome is None and mem.marks.best is not None]
    if tc.polish_iterations > 0 and ready:  # a model whose training fit is at the sensor noise has nothing to polish
        tm = train_mask(problem, ref.batch)
        noise = noise_fit(ref.batch, tm, output_spread(ref.batch.obs[tm]))
        ready = [mem for mem in ready if mem.marks.worth_polishing(noise)]
    if ready and tc.polish_iterations > 0:  # every model with a checkpoint, from its best one, as train() polishes
        for mem in ready:
            mem.hybrid.load_state_dict(mem.marks.best_state())
            mem.done, mem.marks.since_best = False, 0
        stack = Stack(ready, problem, ref, plan, cfg)

        def polished(k: int, loss: torch.Tensor, fit: torch.Tensor) -> bool:
            checkpoint(list(range(stack.size)), last + k, loss, fit)
            return all(mem.done for mem in stack.members)

        def regroup() -> list[torch.Tensor] | None:
            if not any(mem.done for mem in stack.members):
                return None
            drop_done()  # fewer rows: a new L-BFGS over the rest
            return _masked(stack)

        polish_lbfgs(stack.losses, _masked(stack), tc.polish_iterations, tc.eval_every, polished, regroup)
    for mem in members:  # every checkpoint failed: the last failure is the outcome
        if mem.outcome is None and mem.marks.best is None:
            mem.outcome = mem.marks.failed or TrainingDiverged("no checkpoint was evaluated")
    return members


def _masked(stack: Stack) -> list[torch.Tensor]:
    """The stack's trained tensors, each gradient masked to its real entries (padded units stay zero
    under L-BFGS as under the stack's own Adam step)."""
    for p, mk, *_ in stack.params:
        if mk is not None:
            p.register_hook(lambda g, mk=mk: torch.where(mk, g, torch.zeros_like(g)))
    return [p for p, *_ in stack.params]


def _final_batched(done: list[Member], problem: Problem, ref: Reference, plan: Shooting, cfg: TrainingSettings,
                   sim: dict[str, Any]) -> dict[int, tuple[dict[str, float], torch.Tensor] | BaseException]:
    """Every finished model's best checkpoint simulated on every experiment in one batched solve, by slot."""
    for mem in done:
        mem.hybrid.load_state_dict(mem.marks.best_state())
    stack = Stack(done, problem, ref, plan, cfg)  # sorted by activation: map results back by slot
    outcomes = stack.evaluate(list(range(stack.size)), sim, full=True)
    return {mem.slot: outcome for mem, outcome in zip(stack.members, outcomes)}


def _result(mem: Member, problem: Problem, ref: Reference, sim: dict[str, Any],
            final: tuple[dict[str, float], torch.Tensor] | BaseException | None, figures: bool) -> TrainResult | BaseException:
    """The model's best checkpoint as train() returns it: its own HybridModel, evaluated on its own
    (``final`` None) or with the metrics of the final batched evaluation."""
    hybrid = mem.hybrid
    hybrid.load_state_dict(mem.marks.best_state())
    if isinstance(final, BaseException):
        return final
    if final is None:
        try:
            metrics, y, batch = evaluate_with(hybrid, problem, sim)
        except TrainingDiverged as exc:
            return exc
    else:
        metrics, y = dict(final[0]), final[1]
        batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    metrics["checkpoints.failed"] = mem.marks.failures
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=mem.marks.history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref) if figures else {},
        hybrid=hybrid,
    )
