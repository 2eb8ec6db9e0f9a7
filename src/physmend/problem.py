"""The problem every stage works on: the user's model (simplified, compiled) and their experiments."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from physmend.device import CPU, resolve_device
from physmend.modeling import CompiledModel, SimplifiedModel, compile_model, load_model

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
    name = str(cfg.simulate.dtype)
    if name not in DTYPES:
        from physmend.config import ConfigError

        raise ConfigError(f"simulate.dtype must be one of {sorted(DTYPES)}, but got {name!r}")
    return DTYPES[name]


def load_problem(cfg: Any) -> Problem:
    """Build, simplify and compile ``cfg.model``; load and validate ``cfg.data`` against it.

    Reads only: every check on the user's model and data happens here, before any stage writes.
    """
    from physmend.data import load_experiments

    threads = int(cfg.get("threads", 1) or 1)
    if torch.get_num_threads() != threads:  # small solves: thread hand-off costs more than it saves
        torch.set_num_threads(threads)
    dtype = dtype_of(cfg)
    device = resolve_device(cfg.get("device", "auto"))
    model = load_model(str(cfg.model.builder), cfg.model.get("options") or {}, cfg.model.get("corrections")).simplify()
    experiments = load_experiments(cfg.data, model)
    from physmend.data.config import time_unit_of

    return Problem(model=model, compiled=compile_model(model), experiments=experiments, dtype=dtype,
                   time_unit=time_unit_of(cfg.data), device=device)
