"""Whole-trajectory metrics: ``val.rmse``, ``train.rmse``, per-experiment RMSE (test experiments
report only) and the checkpoint problem without test experiments. Imports ``drive``, ``hybrid``,
``outcome``, ``reference``.

A hybrid whose training solve takes drives (:func:`~physmend.ude.drive.drivable`) is simulated whole
with its drive table (:func:`~physmend.ude.drive.drive_table`): the same function, the input-dependent
work done once per input knot instead of at every right-hand side (a checkpoint of the cargo box:
the same 844 Rodas4 iterations, about a quarter less time; metrics equal to about 1e-9).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any
import dataclasses
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch, SimulationError, make_batch
from physmend.simulate.batch import own_stops
from physmend.simulate.initial import estimate_initial, has_unknown
from physmend.ude.hybrid import HybridModel
from physmend.ude.outcome import TrainingDiverged
from physmend.ude.drive import drivable, drive_table, table_fits
from physmend.ude.reference import clocked, solver_options, train_mask, _val_mask, held_out_apart, simulate_with, with_stops


def _pooled(err: torch.Tensor, mask: torch.Tensor) -> float:
    """RMSE of ``err`` where ``mask``; NaN entries (not measured) are left out, an infinite one
    (measured, but the model's output is not finite) makes it infinite."""
    e = err[mask]
    e = e[~torch.isnan(e)]
    return float(e.pow(2).mean().sqrt()) if e.numel() else float("nan")


def evaluate(hybrid: HybridModel, problem: Problem, cfg: Any | None = None, *, sim: dict[str, Any] | None = None) -> dict[str, float]:
    """Whole-trajectory metrics of ``hybrid`` on every experiment (single shooting).

    ``val.rmse``: pooled RMSE over validation samples (output units; outputs scaled by their
    training spread when their units differ); ``train.rmse`` likewise on training samples;
    ``rmse.<experiment>.<output>`` per experiment and output (test experiments: report only).
    """
    return evaluate_with(hybrid, problem, sim or solver_options(cfg))[0]


def metrics_of(problem: Problem, batch: Batch, y: torch.Tensor) -> dict[str, float]:
    """Metrics (see :func:`evaluate`) of whole-trajectory outputs ``y (T, B, k)`` on ``batch``."""
    measured = torch.isfinite(batch.obs)
    # (T, B, k): NaN where not measured; inf where measured but the model's output is not finite
    # (a hybrid that diverged part-way is no fit over the rest of its record)
    err = torch.where(measured & ~torch.isfinite(y), torch.inf, y - batch.obs)
    units = {problem.model.units.get(o, "") for o in problem.model.output_names}
    if len(units) > 1:
        scale = torch.nan_to_num(batch.obs[train_mask(problem, batch)], nan=0.0).std(0).clamp_min(1e-12)
        scaled = err / scale
    else:
        scaled = err
    tm, vm = train_mask(problem, batch), _val_mask(problem, batch)
    metrics = {"val.rmse": _pooled(scaled, vm), "train.rmse": _pooled(scaled, tm)}
    is_test = torch.tensor([e.role == "test" for e in problem.experiments])
    test = is_test[None, :].expand_as(tm)
    if bool(test.any()):
        # a test experiment whose outputs left the finite range where measured has no RMSE: counted
        # in test.failed, and test.rmse is NaN rather than the RMSE of the others
        sq = torch.where(measured, scaled, 0.0).pow(2).sum(dim=(0, 2))  # (B,)
        off = (~torch.isfinite(sq) | (~torch.isfinite(y) & measured).any(-1).any(0)) & is_test
        metrics["test.failed"] = float(off.sum())
        metrics["test.rmse"] = math.nan if bool(off.any()) else _pooled(scaled, test)
    for b, e in enumerate(problem.experiments):
        for j, out in enumerate(problem.model.output_names):
            col = err[:, b, j]
            col = col[~torch.isnan(col)]
            metrics[f"rmse.{e.id}.{out}"] = float(col.pow(2).mean().sqrt()) if col.numel() else float("nan")
    if not math.isfinite(metrics["val.rmse"]) or math.isinf(metrics["train.rmse"]):
        raise TrainingDiverged("validation or training RMSE is not finite (the hybrid trajectory left the finite range)")
    return metrics


def checkpoint_problem(problem: Problem) -> Problem:
    """``problem`` without its test experiments: all that checkpoints (``val.rmse``, ``train.rmse``)
    need. Test experiments are report-only; simulating them at every checkpoint would cost a
    whole-trajectory solve each for figures nobody reads until the end."""
    keep = [e for e in problem.experiments if e.role != "test"]
    return problem if len(keep) == len(problem.experiments) else dataclasses.replace(problem, experiments=keep)


#: a whole-trajectory solve of a hybrid stops once a state is this many training ranges beyond
#: its training range (:meth:`~physmend.ude.hybrid.HybridSpec.box`): that model has diverged, and an
#: adaptive solver would otherwise chase it for minutes
LEAVE_MARGIN = 100.0


def guarded(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
            limits: tuple[torch.Tensor, torch.Tensor] | None, ids: list[str], state_names: list[str]
            ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """``rhs(u (B, n), x)`` that raises :class:`SimulationError` (naming the experiment ``ids[b]``
    and the state) when a state leaves ``limits = (lo, hi)`` or becomes NaN (``lo``, ``hi`` each ``(n,)``; None: only NaN)."""
    # without limits only a NaN state stops the solve (an adaptive solver would carry it to the end)
    lo, hi = limits if limits is not None else (torch.tensor(-torch.inf), torch.tensor(torch.inf))

    def f(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        # one clamp and one comparison per evaluation (a NaN state is not equal to its clamp either)
        if not torch.equal(u.clamp(lo, hi), u):
            out = (u < lo) | (u > hi) | torch.isnan(u)
            b, j = (int(v) for v in torch.nonzero(out.reshape(-1, u.shape[-1]))[0])
            flat = u.reshape(-1, u.shape[-1])
            value = float(flat[b, j])
            if value != value:
                raise SimulationError(f"the hybrid diverged in experiment {ids[b % len(ids)]!r}: state "
                                      f"{state_names[j]!r} is NaN")
            bound = float(hi[j] if value > hi[j] else lo[j])
            raise SimulationError(
                f"the hybrid diverged in experiment {ids[b % len(ids)]!r}: state {state_names[j]!r} reached "
                f"{value:.4g}, past {bound:.4g} ({LEAVE_MARGIN:g} ranges beyond its range in training)")
        return rhs(u, x)

    return f


def evaluate_with(hybrid: HybridModel, problem: Problem, sim: dict[str, Any]) -> tuple[dict[str, float], torch.Tensor, Batch]:
    """Metrics, outputs ``(T, B, k)`` and batch of ``hybrid`` on every experiment of ``problem``.

    The outcome is judged on training and validation experiments only (see :func:`hybrid_states`):
    a test experiment whose solve fails gets NaN outputs, counted in ``test.failed`` (``test.rmse``
    NaN) — it never decides whether a model survives.
    """
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with torch.no_grad():
        states = hybrid_states(hybrid, problem, batch, sim)
        p = hybrid.parameters_for(batch.params)
        y = problem.compiled.outputs(states, batch.inputs.at(batch.t), p[None])
    return metrics_of(problem, batch, y), y, batch


def hybrid_states(hybrid: HybridModel, problem: Problem, batch: Batch, sim: dict[str, Any]) -> torch.Tensor:
    """Whole-trajectory states ``(T, B, n)`` of ``hybrid`` on ``batch`` (every experiment of ``problem``).

    Declared-unknown initial values are this hybrid's own estimates
    (:func:`~physmend.simulate.initial.estimate_initial`); test experiments are solved apart when
    the batched solve fails (:func:`~physmend.ude.reference.held_out_apart`: a failing one is NaN).

    Raises:
        TrainingDiverged: the solve of the training and validation experiments failed.
    """
    names = problem.compiled.state_names
    limits = hybrid.spec.box(LEAVE_MARGIN, problem.dtype)

    def states_of(sub: Batch, u0: torch.Tensor) -> torch.Tensor:
        p = hybrid.parameters_for(sub.params)
        knots = sub.inputs.knots.shape[0]
        if not drivable(hybrid) or not table_fits(sub.size, knots, len(names) + hybrid.spec.widths[0], p.dtype):
            return simulate_with(guarded(hybrid.rhs(p), limits, sub.ids, names), sub, u0, sim)
        states = fixed_step_states(hybrid, p, sub, u0, sim, limits)
        if states is not None:
            return states
        # the same function with the input-dependent work done once per knot (physmend.ude.drive.drive_table)
        rhs, table = drive_table(hybrid, p, sub.inputs)
        return simulate_with(guarded(rhs, limits, sub.ids, names), dataclasses.replace(sub, inputs=table), u0,
                             with_stops(sim, sub))

    def outputs(sub: Batch, u0: torch.Tensor) -> torch.Tensor:
        p = hybrid.parameters_for(sub.params)
        return problem.compiled.outputs(states_of(sub, u0), sub.inputs.at(sub.t), p[None])

    def solve(sub: Batch) -> torch.Tensor:
        # this hybrid's estimates at its previous checkpoint, if any, are where the search starts
        key = tuple(sub.ids)
        u0 = estimate_initial(outputs, sub, names, near=hybrid.initial_estimates.get(key))
        if has_unknown(sub):
            hybrid.initial_estimates[key] = u0
        return states_of(sub, u0)

    try:
        return held_out_apart(problem, batch, solve)
    except SimulationError as exc:
        raise TrainingDiverged(f"whole-trajectory simulation of the hybrid failed: {exc}") from exc


def evaluate_kept(hybrid: HybridModel, problem: Problem, sim: dict[str, Any], keeps: Sequence[Sequence[str]]
                  ) -> list[dict[str, float] | TrainingDiverged]:
    """:func:`evaluate` of ``hybrid`` with only the corrections of the states ``keeps[j]``, for each
    ``j``: its metrics, or the :class:`TrainingDiverged` that variant raises.

    Where the experiments step on a clock each (:func:`~physmend.ude.reference.clocked`), the drives
    apply, no initial value is estimated and no experiment is a test one, every variant is simulated
    in one solve, rows variant-major: each row takes the steps it takes alone, so each variant gets
    the metrics its own evaluation gives (to rounding), for about the cost of one. Otherwise, or
    where that solve fails (a variant diverges), one variant after another. ``hybrid``'s own mask is
    left as it was.
    """
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    together = (len(keeps) > 1 and drivable(hybrid) and clocked(sim, batch) and not has_unknown(batch)
                and all(e.role != "test" for e in problem.experiments)
                and table_fits(len(keeps) * batch.size, batch.inputs.knots.shape[0],
                               len(problem.compiled.state_names) + hybrid.spec.widths[0], problem.dtype))
    if together:
        try:
            y = _kept_outputs(hybrid, problem, batch, sim, keeps)
        except SimulationError:
            together = False
    out: list[dict[str, float] | TrainingDiverged] = []
    if together:
        b = batch.size
        for j in range(len(keeps)):
            try:
                out.append(metrics_of(problem, batch, y[:, j * b:(j + 1) * b]))
            except TrainingDiverged as exc:
                out.append(exc)
        return out
    mask = hybrid.out_mask
    try:
        for names in keeps:
            hybrid.keep_only(list(names))
            try:
                out.append(evaluate(hybrid, problem, sim=sim))
            except TrainingDiverged as exc:
                out.append(exc)
    finally:
        hybrid.out_mask = mask
    return out


def _kept_outputs(hybrid: HybridModel, problem: Problem, batch: Batch, sim: dict[str, Any],
                  keeps: Sequence[Sequence[str]]) -> torch.Tensor:
    """Outputs ``(T, V·B, k)`` of the ``V`` masked variants of ``hybrid`` on ``batch`` in one solve (rows variant-major)."""
    v, b = len(keeps), batch.size
    rows = batch.take(torch.arange(b).repeat(v), ids=[f"{e} (top {len(keep)})" for keep in keeps for e in batch.ids])
    corrected = hybrid.spec.corrected
    mask = torch.tensor([[1.0 if n in keep else 0.0 for n in corrected] for keep in keeps],
                        dtype=hybrid.out_mask.dtype).repeat_interleave(b, 0)  # (V·B, k)
    with torch.no_grad():
        p = hybrid.parameters_for(rows.params)
        limits = hybrid.spec.box(LEAVE_MARGIN, problem.dtype)
        states = fixed_step_states(hybrid, p, rows, rows.u0, sim, limits, mask)
        if states is None:
            rhs, table = drive_table(hybrid, p, rows.inputs, mask)
            states = simulate_with(guarded(rhs, limits, rows.ids, problem.compiled.state_names),
                                   dataclasses.replace(rows, inputs=table), rows.u0, with_stops(sim, rows))
        return problem.compiled.outputs(states, rows.inputs.at(rows.t), p[None])


def fixed_step_states(hybrid: HybridModel, p: torch.Tensor, rows: Batch, u0: torch.Tensor, sim: dict[str, Any],
                      limits: tuple[torch.Tensor, torch.Tensor] | None, mask: torch.Tensor | None = None
                      ) -> torch.Tensor | None:
    """States ``(T, B, n)`` of ``hybrid`` on ``rows`` by :func:`~physmend.ude.fixed_step.rk4_states`
    (each row from the stops its own clock would take), or None where that does not apply or does
    not agree within ``sim``'s tolerances: the adaptive solve then decides. No gradients."""
    from physmend.ude.fixed_step import applies, hybrid_form, rk4_states

    if torch.is_grad_enabled() or not applies(sim, hybrid.spec.activation, u0.device):
        return None
    form = hybrid_form(hybrid, p, rows.inputs, mask)
    if form is None:
        return None
    return rk4_states(form, u0, rows.t, row_stops(rows, sim), sim["rtol"], sim["atol"], limits)


def row_stops(rows: Batch, sim: dict[str, Any]) -> list[torch.Tensor]:
    """Each row's stops as the adaptive solve of ``rows`` with ``sim`` would take them: its own
    clock's (:func:`~physmend.simulate.batch.own_stops`, or ``sim``'s fixed clocks), or with one
    clock for all, the shared times and input knots."""
    stops = sim["options"]["clocks"] if "clocks" in sim["options"] else own_stops(rows)
    if stops is None:
        stops = [torch.unique(torch.cat([rows.t, rows.inputs.knots.to(rows.t.dtype)]))] * rows.size
    return list(stops)
