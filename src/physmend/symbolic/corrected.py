"""The corrected model — the model as written plus formulas, no network — built, simulated, scored
and its constants re-fitted through the simulator (the symbolic stage's and the choice's tools)."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf


def corrected_problem(problem_cfg: Any, corrections: list) -> Any:
    """The problem of ``problem_cfg`` with ``corrections`` attached to their equations (no network);
    each constant is a model parameter (:func:`physmend.modeling.corrections.constant_parameter_name`)."""
    from physmend.modeling import write_corrections
    from physmend.problem import load_problem

    with tempfile.TemporaryDirectory(prefix="physmend-corrected-") as tmp:
        work = OmegaConf.create(OmegaConf.to_container(problem_cfg, resolve=True))
        work.model.corrections = str(write_corrections(Path(tmp) / "candidate.yaml", corrections))
        return load_problem(work)


def simulate_corrected(problem: Any, problem_cfg: Any) -> tuple[Any, str | None]:
    """Whole-trajectory simulation of the corrected model (adaptive solver) on the experiments of
    ``problem`` — every choice passes the training and validation experiments only
    (:func:`physmend.ude.metrics.checkpoint_problem`); test experiments are simulated for the report.

    Returns ``(reference, None)``, or ``(None, why)`` when it cannot be simulated: the solver
    fails on some experiment, or an output of a training or validation experiment is not finite.
    """
    from physmend.simulate import SimulationError
    from physmend.ude.reference import reference

    try:
        ref = reference(problem, problem_cfg, shared_clock=False)  # judged at the records' own times
    except SimulationError as exc:
        return None, str(exc).split(":")[0]
    y = problem.compiled.outputs(ref.states, ref.inputs, ref.batch.params[None])  # (T, B, k)
    checked = [b for b, e in enumerate(problem.experiments) if e.role != "test"]
    if not bool(torch.isfinite(y[:, checked]).all()):
        return None, "non-finite outputs"
    return ref, None


def with_parameters(problem: Any, values: dict[str, float]) -> Any:
    """``problem`` with the parameters ``values`` (name -> value) changed in every experiment."""
    import dataclasses

    names = problem.compiled.parameter_names
    experiments = []
    for e in problem.experiments:
        params = np.array(e.parameters, dtype=float)
        for name, value in values.items():
            params[names.index(name)] = float(value)
        experiments.append(dataclasses.replace(e, parameters=params))
    return dataclasses.replace(problem, experiments=experiments)


def corrected_metrics(problem: Any, ref: Any, *, require_validation: bool = True) -> dict[str, float]:
    """Whole-trajectory metrics (``val.rmse`` …, see :func:`physmend.ude.metrics.metrics_of`) of the
    corrected model from its simulation ``ref`` (:func:`simulate_corrected`)."""
    from physmend.ude.metrics import metrics_of
    from physmend.ude.outcome import TrainingDiverged

    with torch.no_grad():
        y = problem.compiled.outputs(ref.states, ref.inputs, ref.batch.params[None])
    try:
        return metrics_of(problem, ref.batch, y)
    except TrainingDiverged:
        if require_validation:
            raise
        return {}


def refit(problem_cfg: Any, problem: Any, ref: Any, corrections: list, iterations: int, *,
          uncertainty: bool = True, starts: Any = None, recalibrate: list[str] | None = None) -> tuple[list, Any]:
    """Re-fit the constants of ``corrections`` through the simulator (multiple shooting, at most
    ``iterations`` Levenberg–Marquardt steps; :mod:`physmend.symbolic.refit`), together with the
    model parameters ``recalibrate`` (declared uncertain: within their bounds); the model's other
    parameters stay as written (``starts``: shared segment-start guesses, see ``refit_constants``).
    Returns the re-fitted corrections and the fit's outcome (its ``constants`` include the
    re-calibrated parameters)."""
    from physmend.modeling import Correction
    from physmend.modeling.corrections import constant_parameter_name
    from physmend.symbolic.refit import refit_constants

    names = {(c.state, k): constant_parameter_name(problem.model.owner.get(c.state, ""), c.state, k)
             for c in corrections for k in c.constants}
    result = refit_constants(problem, problem_cfg, ref, list(names.values()) + list(recalibrate or []), max_iterations=iterations,
                             uncertainty=uncertainty, starts=starts)
    fitted = [Correction(state=c.state, term=c.term, unit=c.unit, mechanism=c.mechanism,
                         constants={k: result.constants.get(names[(c.state, k)], v) for k, v in c.constants.items()})
              for c in corrections]
    return fitted, result


def recalibratable(problem: Any, corrections: list, problem_cfg: Any = None) -> list[str]:
    """The parameters of ``problem``'s model declared uncertain (with bounds), in declaration order,
    other than the constants of ``corrections`` and other than those the data config sets for some
    experiment (``problem_cfg.data.experiments[*].parameters``, or a value that differs from the
    declared one: a configuration, not a calibration, and a value the proposal could not change):
    the ones a corrected model may re-calibrate (:func:`refit` ``recalibrate``)."""
    from physmend.modeling.corrections import constant_parameter_name

    own = {constant_parameter_name("", c.state, k) for c in corrections for k in c.constants}
    configured: set[str] = set()
    for e in (problem_cfg.data.get("experiments") or []) if problem_cfg is not None else []:
        configured |= {str(k) for k in (e.get("parameters") or {})}
    names = problem.compiled.parameter_names
    values = np.array([np.asarray(e.parameters, dtype=float) for e in problem.experiments])  # (B, n_params)
    return [v.name for v in problem.model.parameters if v.uncertain and v.bounds is not None and v.name not in own
            and v.name not in configured and np.all(values[:, names.index(v.name)] == float(v.value))]
