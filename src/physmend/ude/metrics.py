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
from physmend.ude.reference import _sim_opts, _train_mask, _val_mask, simulate_with


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
