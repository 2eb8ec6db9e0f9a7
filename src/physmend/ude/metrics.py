"""Whole-trajectory metrics: ``val.rmse``, ``train.rmse``, per-experiment RMSE (test experiments
report only) and the checkpoint problem without test experiments. Imports ``hybrid``, ``outcome``,
``reference``.
"""

from __future__ import annotations

from typing import Any
import dataclasses
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch, SimulationError, make_batch
from physmend.ude.hybrid import HybridModel
from physmend.ude.outcome import TrainingDiverged
from physmend.ude.reference import _sim_opts, _train_mask, _val_mask, held_out_apart, simulate_with


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
    is_test = torch.tensor([e.role == "test" for e in problem.experiments])
    test = is_test[None, :].expand_as(tm)
    if bool(test.any()):
        # a test experiment whose outputs left the finite range where measured has no RMSE: counted
        # in test.failed, and test.rmse is NaN rather than the RMSE of the others
        measured = torch.isfinite(batch.obs)
        sq = torch.where(measured, scaled, 0.0).pow(2).sum(dim=(0, 2))  # (B,)
        off = (~torch.isfinite(sq) | (~torch.isfinite(y) & measured).any(-1).any(0)) & is_test
        metrics["test.failed"] = float(off.sum())
        metrics["test.rmse"] = math.nan if bool(off.any()) else _pooled(scaled, test)
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
    """Metrics, outputs ``(T, B, k)`` and batch of ``hybrid`` on every experiment of ``problem``.

    The outcome is judged on training and validation experiments only
    (:func:`~physmend.ude.reference.held_out_apart`): a test experiment whose solve fails gets NaN
    outputs, counted in ``test.failed`` (``test.rmse`` NaN) — it never decides whether a model survives.
    """
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)

    def solve(sub: Batch) -> torch.Tensor:
        p = hybrid.parameters_for(sub.params)
        states = simulate_with(hybrid.rhs(p), sub, sub.u0, sim)
        return problem.compiled.outputs(states, sub.inputs.at(sub.t), p[None])

    with torch.no_grad():
        try:
            y = held_out_apart(problem, batch, solve)
        except SimulationError as exc:
            raise TrainingDiverged(f"whole-trajectory simulation of the hybrid failed: {exc}") from exc
    return metrics_of(problem, batch, y), y, batch
