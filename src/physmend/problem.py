"""The problem every stage works on: the user's model (simplified, compiled) and their experiments."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from physmend.device import CPU, resolve_device
from physmend.modeling import CompiledModel, SimplifiedModel, compile_model, load_model
from physmend.modeling.model import Model
from physmend.modeling.recent import Recent
from physmend.settings import SimulateSettings, group_settings

DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass
class Problem:
    """The simplified and compiled model plus the loaded experiments (see :mod:`physmend.data`)."""

    model: SimplifiedModel
    compiled: CompiledModel
    experiments: list[Any]
    dtype: torch.dtype
    #: the unit of every time (``data.time_unit``: seconds unless declared; any other unit is shown, never converted)
    time_unit: str = "s"
    #: where training and its simulations run (``device``, :mod:`physmend.device`); other stages use the CPU
    device: torch.device = CPU

    def by_role(self, *roles: str) -> list[Any]:
        return [e for e in self.experiments if e.role in roles]


def dtype_of(cfg: Any) -> torch.dtype:
    """The torch dtype of ``simulate.dtype`` (checked: :class:`physmend.settings.SimulateSettings`)."""
    return DTYPES[SimulateSettings.build(cfg.simulate).dtype]


def load_problem(cfg: Any) -> Problem:
    """Build, simplify and compile ``cfg.model``; load and validate ``cfg.data`` against it.

    Reads only: every check on the user's model and data happens here, before any stage writes —
    values beyond ``simulate.dtype`` arithmetic and records with more rows than the solver can pass
    included (:mod:`physmend.data.sanity`).
    """
    from physmend.data import load_experiments

    from physmend.cpus import threads as thread_count

    top = group_settings(cfg, "")  # seed, threads, device: checked, their defaults conf/config.yaml's
    threads = thread_count(top.threads)  # torch's and the compiled training solve's (compiled_solve)
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    dtype = dtype_of(cfg)
    device = resolve_device(top.device)
    model, compiled = simplified_and_compiled(
        load_model(str(cfg.model.builder), cfg.model.get("options") or {}, cfg.model.get("corrections")))
    experiments = load_experiments(cfg.data, model, dtype=SimulateSettings.build(cfg.simulate).dtype)
    from physmend.data.config import time_unit_of
    from physmend.data.sanity import check_sampling

    problem = Problem(model=model, compiled=compiled, experiments=experiments, dtype=dtype,
                      time_unit=time_unit_of(cfg.data), device=device)
    check_sampling(experiments, cfg.simulate, time_unit=problem.time_unit, fastest=lambda: _fastest(problem))
    return problem


#: simplified and compiled models of this process, by the whole model as built (:func:`model_text`),
#: the most recently used last: a model built again with the same equations (every stage of
#: ``physmend discover`` builds the user's model) is not simplified and compiled again (seconds for
#: tens of states); a model file edited in between builds other equations and is compiled anew
_COMPILED: Recent[tuple[SimplifiedModel, CompiledModel]] = Recent(4)


def model_text(model: Model) -> str:
    """Everything of ``model`` as canonical text: every field of every declaration, each sympy
    expression as :func:`sympy.srepr` (symbols with their assumptions), dictionaries in key order."""
    import dataclasses

    import sympy as sp

    def text(obj: Any) -> str:
        if isinstance(obj, sp.Basic):
            return sp.srepr(obj)
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            return type(obj).__name__ + "(" + ",".join(f"{f.name}={text(getattr(obj, f.name))}"
                                                        for f in dataclasses.fields(obj)) + ")"
        if isinstance(obj, dict):
            return "{" + ",".join(f"{text(k)}:{text(v)}" for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))) + "}"
        if isinstance(obj, (list, tuple)):
            return "[" + ",".join(text(v) for v in obj) + "]"
        return repr(obj)

    return text(model)


def simplified_and_compiled(model: Model) -> tuple[SimplifiedModel, CompiledModel]:
    """``model`` simplified and compiled (:func:`compile_model`), or what this process made of a
    model with the same :func:`model_text` (they are never modified once made)."""
    def make() -> tuple[SimplifiedModel, CompiledModel]:
        simplified = model.simplify()
        return simplified, compile_model(simplified)

    return _COMPILED.get(model_text(model), make)


def _fastest(problem: Problem) -> float:
    """The fastest time constant of the model as written at the training records' starts."""
    import dataclasses

    from physmend.data.sanity import record_starts

    return fastest_time_constant(dataclasses.replace(problem, experiments=record_starts(problem.experiments)))


def fastest_time_constant(problem: Problem, states: torch.Tensor | None = None, inputs: torch.Tensor | None = None,
                          params: torch.Tensor | None = None) -> float:
    """``1 / max |λ|`` of the model's Jacobian at the given points (inf when every λ is 0).

    ``states (P, n)``, ``inputs (P, m)``, ``params (P, k)``; without them, the start states of the
    training experiments with their inputs at their first time.
    """
    from physmend.simulate import make_batch

    model = problem.compiled
    if states is None:
        train = [e for e in problem.experiments if e.role == "train"] or list(problem.experiments)
        batch = make_batch(train, model, problem.dtype)
        states = batch.u0
        inputs = batch.inputs.at(batch.t[:1])[0]  # (B, m), m may be 0
        params = batch.params
    assert inputs is not None and params is not None
    n = states.shape[-1]
    with torch.no_grad():
        h = 1e-6 * states.abs().clamp_min(1.0)  # (P, n)
        eye = torch.eye(n, dtype=states.dtype)
        up = states[None] + eye[:, None, :] * h[None]  # (n, P, n): state i perturbed in block i
        down = states[None] - eye[:, None, :] * h[None]
        x = inputs[None].expand(n, *inputs.shape)
        p = params[None].expand(n, *params.shape)
        diff = model.rhs(up, x, p) - model.rhs(down, x, p)  # (n, P, n)
        jac = (diff / (2 * h.T[:, :, None])).permute(1, 2, 0)  # (P, n_out, n_in)
        jac = torch.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0)
        rho = float(torch.linalg.eigvals(jac).abs().max()) if jac.numel() else 0.0
    return 1.0 / rho if rho > 0 and math.isfinite(rho) else math.inf
