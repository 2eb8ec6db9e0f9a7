"""Several hybrid models (a group of sweep trials) trained together in one batched solve.

On small ODEs, per-operation dispatch, not arithmetic, dominates an epoch: a stack of ``M``
same-shaped networks costs about as much as one (the 2-state oscillator of the tests: 16 models
per epoch for twice the time of one). On larger ones arithmetic takes over from a few models on
(the 28-state cargo box: about 2.5-3x less time per model from M = 4 to 32; padding mixed widths
and depths to the largest costs part of that, see ``stack_key(architecture=True)``).
:func:`train_stack` trains ``M`` configurations
as one multiple-shooting solve over ``M·S`` rows (``S`` segments per model) and evaluates the
still-active models in one whole-trajectory solve over ``M·B`` rows (``B`` train and validation
experiments; test experiments only at the end); their derivative-matching warm starts are one
batched regression over shared forced trajectories. Yet every model remains exactly its own
trial, as :func:`physmend.ude.train.train` would run it:

* its own architecture ``(width, depth, activation)``: networks are padded to the largest width
  and depth of the stack; padded units have zero weights that never move (their gradients are
  masked, so neither AdamW nor weight decay touches them), a shallower network skips the extra
  hidden layers (``h ← h``), and each model's rows pass through its own activation;
* its own initialisation (seed) and warm start, built on its own :class:`HybridModel` exactly as
  ``train()`` builds it, then copied into the padded tensors;
* its own AdamW (learning rate, weight decay, schedule and warm-up ramp), gradient clipping
  (norm 10 per model), trainable segment starts and jointly estimated parameters;
* its own evaluations, early stopping, best checkpoint and report callback; a model that stops
  (patience, divergence, an exception raised by ``report``) leaves the stack, the others go on;
* its own :class:`TrainResult` at the end, with an ordinary :class:`HybridModel` of its own
  architecture (artifacts and reloading are unchanged).

What cannot be identical: batched matrix products (``baddbmm``) and reductions over padded
tensors round differently from ``nn.Linear`` on one model (differences ~1e-15 relative per step),
and the adaptive whole-trajectory solver picks one step size for all rows of a batched
evaluation, so checkpoint metrics agree with a solo evaluation to the solver tolerance. The final
metrics of each model come from its own solo evaluation, exactly as ``train()`` computes them, or
(``final_eval="batched"``, as sweeps use it) from one batched solve of all finished models.

Here: the shared settings (:data:`SHARED_KEYS`, :func:`stack_key`), :func:`train_stack`, the shared
epoch loop and the final evaluations. The pieces: ``stack_net`` (padded networks), ``stack_plan``
(reference and plan, once per problem), ``stack`` (the batched model, its losses and step),
``stack_members`` (each model prepared, the shared warm start). Imports those and ``artifacts``,
``hybrid``, ``metrics``, ``outcome``, ``reference``, ``shooting``, ``warmstart`` (and ``timescale``,
lazily); never ``train``: the two trainers are siblings on the same pieces.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any
import copy
import json
import math

from omegaconf import DictConfig, OmegaConf
import torch

from physmend.device import placed
from physmend.problem import Problem
from physmend.simulate import make_batch
from physmend.ude.artifacts import artifacts_of, fit_figures
from physmend.ude.hybrid import UDEConfigError
from physmend.ude.stack import _Member, _Stack
from physmend.ude.stack_members import _check_same_shape, _prepare, _shared_warm_start, _warm_fit, _warm_settings
from physmend.ude.stack_plan import _setup
from physmend.ude.metrics import _evaluate
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.polish import Polisher, fit_at, polish_iterations, worth_polishing
from physmend.ude.reference import Reference, _sim_opts, train_mask
from physmend.ude.schedule import _lr_schedule, cycle_of, fit_gain, fit_progressed, restarts, stops_at
from physmend.ude.shooting import BOX_MARGIN, Shooting, output_spread, noise_fit, pinned_starts, segments_finite
from physmend.ude.warmstart import Forced, recall_derived, remember_derived


__all__ = ["SHARED_KEYS", "stack_key", "train_stack"]

#: Settings every model of one stack must share: they shape the common solve (or the problem).
SHARED_KEYS: tuple[str, ...] = (
    "model",
    "data",
    "simulate",
    "train.step",
    "train.segment_length",
    "train.segment_samples",
    "train.epochs",
    "train.restarts",
    "train.schedule",
    "train.eval_every",
    "train.patience",
    "train.patience_fit_gain",
    "train.continuity_weight",
    "train.estimate_parameters",
    "ude.corrected",
    "ude.inputs",
)

_LINEAR_KEY = "ude.depth == 0"  # a linear correction (no hidden layer) cannot be padded into an MLP

Report = Callable[[int, int, dict[str, float]], None]


def _plain(value: Any) -> Any:
    """A hashable, comparable form of a config value (containers as canonical JSON)."""
    if isinstance(value, DictConfig) or OmegaConf.is_list(value):
        return json.dumps(OmegaConf.to_container(value, resolve=True), sort_keys=True)
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, sort_keys=True)
    return value


def stack_key(cfg: DictConfig, *, architecture: bool = False) -> tuple[tuple[str, Any], ...]:
    """The settings that must agree for configurations to train in one stack, as ``(key, value)`` pairs.

    Trials whose keys are equal can be passed together to :func:`train_stack`; they may differ in
    ``seed``, ``ude.width``, ``ude.depth`` (all ≥ 1, or all 0), ``ude.activation``,
    ``ude.output_scale``, ``train.lr``, ``train.weight_decay``, ``train.sparsity`` and the
    warm-start settings. ``architecture=True`` adds width, depth and activation to the key: stacks
    of one architecture need no padding, which pays where arithmetic, not dispatch, dominates.
    """
    pairs = [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in SHARED_KEYS]
    pairs.append((_LINEAR_KEY, int(cfg.ude.depth) == 0))
    if architecture:
        pairs += [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in ("ude.width", "ude.depth", "ude.activation")]
    return tuple(pairs)


def _check_shared(cfgs: Sequence[DictConfig]) -> None:
    first = dict(stack_key(cfgs[0]))
    for i, cfg in enumerate(cfgs[1:], 1):
        for key, value in stack_key(cfg):
            if value != first[key]:
                raise UDEConfigError(
                    f"train_stack: every model of a stack must have the same `{key}` (it shapes the shared solve), "
                    f"but model 0 has {first[key]!r} and model {i} has {value!r}; group trials by stack_key()"
                )


def train_stack(cfgs: Sequence[DictConfig], problem: Problem, *, report: Report | None = None,
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
    _check_shared(cfgs)  # before the problem is used
    with placed(problem.device):  # physmend.device; every result's model comes back on the CPU
        results = _train_stack(cfgs, problem, report, final_eval, figures)
    return [r.on_cpu() if isinstance(r, TrainResult) else r for r in results]


def _train_stack(cfgs: Sequence[DictConfig], problem: Problem, report: Report | None, final_eval: str,
                 figures: bool) -> list[TrainResult | BaseException]:
    """:func:`train_stack` on the current default device."""
    from physmend.ude.timescale import check_budget, resolve_times

    ref, _ = _setup(problem, cfgs[0], plan=False)
    cfgs = [resolve_times(cfg, problem, ref) for cfg in cfgs]  # 'auto' time settings, as train() resolves them
    cfg0 = cfgs[0]
    ref, plan = _setup(problem, cfg0)
    check_budget(plan, problem, cfgs)
    results: list[TrainResult | BaseException | None] = [None] * len(cfgs)
    members: list[_Member] = []
    warm_settings = {_warm_settings(cfg) for cfg in cfgs}
    batched_warm = len(warm_settings) == 1 and next(iter(warm_settings))[0] == "auto"
    for i, cfg in enumerate(cfgs):
        try:
            members.append(_prepare(cfg, problem, ref, plan, i, warm=not batched_warm))
        except Exception as exc:  # noqa: BLE001 - train(cfg) would have raised it: this trial's outcome
            results[i] = exc
    if members:
        _check_same_shape(members)
        warm = _shared_warm_start(members, problem, ref, plan) if batched_warm else None
        finished = _run(members, problem, ref, plan, cfg0, report, warm)
        sim = _sim_opts(cfg0)
        done = [mem for mem in finished if mem.outcome is None]
        final = _final_batched(done, problem, ref, plan, cfg0, sim) if final_eval == "batched" and done else {}
        for mem in finished:
            results[mem.slot] = mem.outcome if mem.outcome is not None else _result(mem, problem, ref, sim, final.get(mem.slot), figures)
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def _drop_unstable_warm_starts(members: list[_Member], initial: list[dict[str, Any]], ref: Reference,
                               plan: Shooting) -> None:
    """A member whose warm-started network leaves the finite range on its own segments goes back to
    its network as initialised and trains without a warm start (as :func:`train` does)."""
    pinned, _, _ = pinned_starts(ref.batch, plan, members[0].hybrid.compiled.state_names)
    fixed_first = ref.batch.u0[plan.exp_index]
    params_seg = ref.batch.params[plan.exp_index]
    box = members[0].hybrid.spec.box(BOX_MARGIN, ref.batch.t.dtype)  # as the stack trains (states held in it)
    for mem, state in zip(members, initial):
        rhs = mem.hybrid.rhs(mem.hybrid.parameters_for(params_seg))
        if not segments_finite(rhs, torch.where(pinned, fixed_first, mem.seg0), plan, box):
            mem.hybrid.load_state_dict(state)
            mem.forced, mem.warm_key = None, None
            mem.lrs = _lr_schedule(mem.cfg, warm=False)


def _run(members: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig,
         report: Report | None, warm: tuple[Forced, int, int] | None = None) -> list[_Member]:
    """The shared epoch loop (after the batched warm start ``warm``: forced trajectories, iterations,
    window); returns every member, each with a best checkpoint or an outcome."""
    tc = cfg.train
    if warm is not None:
        initial = [copy.deepcopy(mem.hybrid.state_dict()) for mem in members]
        _warm_fit(members, problem, ref, plan, cfg, *warm)
        _drop_unstable_warm_starts(members, initial, ref, plan)
    stack = _Stack(members, problem, ref, plan, cfg)
    if warm is not None:
        stack.chain_starts()
    sim = _sim_opts(cfg)
    checked_name = ("checkpoint", json.dumps(sim, sort_keys=True, default=str), id(problem))
    epochs = int(tc.epochs)
    eval_every = max(1, int(tc.eval_every))
    patience = int(tc.patience)
    gain = fit_gain(tc)

    def checkpoint(positions: list[int], epoch: int, loss: torch.Tensor | None, fit: torch.Tensor | None,
                   known: dict[int, dict[str, float]] | None = None) -> None:
        """Evaluate the models at ``positions`` (``known``: metrics of some already, by position); mark
        those whose patience ran out or that failed as done."""
        known = known or {}
        todo = [pos for pos in positions if pos not in known]
        outcomes: dict[int, tuple[dict[str, float], Any] | BaseException] = {pos: (known[pos], None) for pos in positions if pos in known}
        if todo:
            outcomes.update(zip(todo, stack.evaluate(todo, sim)))
        for pos in positions:
            outcome = outcomes[pos]
            mem = stack.members[pos]
            if isinstance(outcome, TrainingDiverged):  # this checkpoint's whole trajectory failed: not a
                # candidate, but training goes on (the next checkpoint may be fine); patience counts it
                mem.failed = outcome
                mem.history.append({"epoch": float(epoch), "loss": float("nan") if loss is None else float(loss[pos]),
                                    "fit_loss": float("nan") if fit is None else float(fit[pos]),
                                    "val.rmse": math.inf, "train.rmse": math.inf})
                mem.since_best += 1
                # patience runs out only after a good checkpoint: a start that diverges (e.g. a warm
                # start out of its data) is what training is there to repair
                if patience > 0 and mem.best is not None and mem.since_best >= patience:
                    mem.done = True
                continue
            if isinstance(outcome, BaseException):
                mem.outcome, mem.done = outcome, True
                continue
            metrics, _ = outcome
            if epoch == 0 and pos not in known and mem.warm_key is not None:
                remember_derived(mem.warm_key, checked_name, (problem, dict(metrics)))
            row = {"epoch": float(epoch),
                   "loss": float("nan") if loss is None else float(loss[pos]),
                   "fit_loss": float("nan") if fit is None else float(fit[pos]),
                   **{k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")}}
            mem.history.append(row)
            if mem.best is None:
                mem.good_cycle = cycle_of(epoch, epochs)
            fitting, mem.best_fit = fit_progressed(metrics["train.rmse"], mem.best_fit, gain)
            if mem.best is None or metrics["val.rmse"] < mem.best[0]:
                stack.write_back(pos)
                mem.best = (metrics["val.rmse"], copy.deepcopy(mem.hybrid.state_dict()), metrics)
                mem.since_best = 0
            elif fitting:
                mem.since_best = 0
            else:
                mem.since_best += 1
            if report is not None:
                try:
                    report(mem.slot, epoch, row)
                except Exception as exc:  # noqa: BLE001 - e.g. a pruning signal: this model stops
                    mem.outcome, mem.done = exc, True
                    continue
            if patience > 0 and mem.since_best >= patience:
                mem.done = True

    def drop_done() -> None:
        stack.keep([i for i, mem in enumerate(stack.members) if not mem.done])

    warm = [i for i, mem in enumerate(stack.members) if mem.forced is not None]
    if warm:  # a warm start itself is a candidate (it may already be the best fit), as in train()
        # its evaluation follows from the warm start alone: an earlier stack of this process may have it
        known = {}
        for pos in warm:
            key = stack.members[pos].warm_key
            stored = None if key is None else recall_derived(key, checked_name)
            if stored is not None and stored[0] is problem:
                known[pos] = dict(stored[1])
        checkpoint(warm, 0, None, None, known)
        drop_done()
    cycles = 1 + restarts(tc)
    epoch = 0
    for epoch in range(1, epochs * cycles + 1):
        if epoch > epochs and (epoch - 1) % epochs == 0:  # a cycle ended: the models that need it go on
            for mem in stack.members:  # with their schedule restarted (stops_at)
                mem.done = mem.done or stops_at(epoch, epochs, mem.good_cycle)
            drop_done()
        if not stack.members:
            break
        loss, fit = stack.losses()
        ok = torch.isfinite(loss.detach())
        for pos in torch.nonzero(~ok).flatten().tolist():
            mem = stack.members[pos]
            lr0 = float(mem.cfg.train.lr)
            mem.outcome = TrainingDiverged(f"training loss became non-finite at epoch {epoch} (lr {lr0:g}); "
                                           "try a smaller train.lr or train.step")
            mem.done = True
        if bool(ok.any()):
            lr = torch.tensor([mem.lrs[(epoch - 1) % epochs] for mem in stack.members], dtype=stack.dtype)
            stack.step(loss, lr, torch.nonzero(ok).flatten())
        loss, fit = loss.detach(), fit.detach()
        if epoch % eval_every == 0 or epoch % epochs == 0:
            live = [i for i, mem in enumerate(stack.members) if not mem.done]
            if live:
                checkpoint(live, epoch, loss, fit)
        drop_done()
    last = max((int(r["epoch"]) for mem in members for r in mem.history), default=epoch)  # the last checkpoint
    polish = polish_iterations(tc)
    ready = [mem for mem in members if mem.outcome is None and mem.best is not None]
    if polish > 0 and ready:  # a model whose training fit is at the sensor noise has nothing to polish
        tm = train_mask(problem, ref.batch)
        noise = noise_fit(ref.batch, tm, output_spread(ref.batch.obs[tm]))
        ready = [mem for mem in ready if mem.best is not None and worth_polishing(fit_at(mem.history, mem.best[0]), noise)]
    if polish > 0 and ready:  # every model with a checkpoint, from its best one, as train() polishes
        for mem in ready:
            assert mem.best is not None
            mem.hybrid.load_state_dict(mem.best[1])
            mem.done, mem.since_best = False, 0
        stack = _Stack(ready, problem, ref, plan, cfg)
        polisher = Polisher(_masked(stack))
        done_iters = 0
        while done_iters < polish and stack.members:
            step = min(eval_every, polish - done_iters)
            if not polisher.run(stack.losses, step):
                break
            done_iters += step
            with torch.no_grad():
                loss, fit = stack.losses()
            checkpoint(list(range(stack.size)), last + done_iters, loss, fit)
            if polisher.stalled:
                break
            if any(mem.done for mem in stack.members):  # fewer rows: a new L-BFGS over the rest
                drop_done()
                polisher = Polisher(_masked(stack))
    for mem in members:  # every checkpoint failed: the last failure is the outcome
        if mem.outcome is None and mem.best is None:
            mem.outcome = mem.failed or TrainingDiverged("no checkpoint was evaluated (train.epochs < 1?)")
    return members


def _masked(stack: _Stack) -> list[torch.Tensor]:
    """The stack's trained tensors, each gradient masked to its real entries (padded units stay zero
    under L-BFGS as under the stack's own Adam step)."""
    for p, mk, *_ in stack.params:
        if mk is not None:
            p.register_hook(lambda g, mk=mk: torch.where(mk, g, torch.zeros_like(g)))
    return [p for p, *_ in stack.params]


def _final_batched(done: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig,
                   sim: dict[str, Any]) -> dict[int, tuple[dict[str, float], torch.Tensor] | BaseException]:
    """Every finished model's best checkpoint simulated on every experiment in one batched solve, by slot."""
    for mem in done:
        assert mem.best is not None
        mem.hybrid.load_state_dict(mem.best[1])
    stack = _Stack(done, problem, ref, plan, cfg)  # sorted by activation: map results back by slot
    outcomes = stack.evaluate(list(range(stack.size)), sim, full=True)
    return {mem.slot: outcome for mem, outcome in zip(stack.members, outcomes)}


def _result(mem: _Member, problem: Problem, ref: Reference, sim: dict[str, Any],
            final: tuple[dict[str, float], torch.Tensor] | BaseException | None, figures: bool) -> TrainResult | BaseException:
    """The model's best checkpoint as train() returns it: its own HybridModel, evaluated on its own
    (``final`` None) or with the metrics of the final batched evaluation."""
    assert mem.best is not None
    hybrid = mem.hybrid
    hybrid.load_state_dict(mem.best[1])
    if isinstance(final, BaseException):
        return final
    if final is None:
        try:
            metrics, y, batch = _evaluate(hybrid, problem, sim)
        except TrainingDiverged as exc:
            return exc
    else:
        metrics, y = dict(final[0]), final[1]
        batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    metrics["checkpoints.failed"] = float(sum(math.isinf(r["val.rmse"]) for r in mem.history))
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=mem.history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref) if figures else {},
        hybrid=hybrid,
    )
