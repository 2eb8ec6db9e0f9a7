"""physmend: find the physics a model is missing.

From Python (names loaded on first use, so ``import physmend`` stays cheap)::

    import physmend
    d = physmend.discover("cstr", "cstr", discover={"n_trials": 1, "budget": None})
    d.formulas, d.fit          # sympy terms; RMSE before/after (pandas)
    physmend.accept(d)

One function per stage (``diagnose``, ``sweep``, ``mask``, ``sensitivity``, ``symbolic``, ``propose``,
``accept``, ``reject``, ``export``), each returning a typed result (:mod:`physmend.api`). Building
blocks live in subpackages: :mod:`physmend.modeling` (write and simplify models), :mod:`physmend.data`
(telemetry), :mod:`physmend.simulate` (batched simulation), :mod:`physmend.stages` (the pipeline) and
:mod:`physmend.tracking` (MLflow conventions).
"""

from __future__ import annotations

import sys
import types
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

#: public name -> the module that defines it (imported on first use)
_LAZY = {
    "discover": "physmend.api",
    "diagnose": "physmend.api",
    "mask": "physmend.api",
    "sensitivity": "physmend.api",
    "propose": "physmend.api",
    "accept": "physmend.api",
    "reject": "physmend.api",
    "export": "physmend.api",
    "Experiment": "physmend.api",
    "Dataset": "physmend.api",
    "Discovery": "physmend.api",
    "Diagnosis": "physmend.api",
    "SweepResult": "physmend.api",
    "MaskResult": "physmend.api",
    "SensitivityResult": "physmend.api",
    "SymbolicResult": "physmend.api",
    "Proposal": "physmend.api",
    "Decision": "physmend.api",
    "ExportResult": "physmend.api",
    "StageResult": "physmend.api",
    "PhysmendError": "physmend.exceptions",
    "Model": "physmend.modeling",
}

__all__ = ["__version__", *sorted([*_LAZY, "sweep", "symbolic"])]

if TYPE_CHECKING:
    from physmend.api import (  # noqa: F401
        Dataset, Decision, Diagnosis, Discovery, Experiment, ExportResult, MaskResult, Proposal,
        SensitivityResult, StageResult, SweepResult, SymbolicResult, accept, diagnose, discover, export, mask,
        propose, reject, sensitivity,
    )
    from physmend.exceptions import PhysmendError  # noqa: F401
    from physmend.modeling import Model  # noqa: F401


#: stage functions whose names are also subpackages (``physmend.sweep``, ``physmend.symbolic``)
_BOTH = ("sweep", "symbolic")


class _StageModule(types.ModuleType):
    """A subpackage that is also the API function of its name: ``physmend.sweep(...)`` runs the stage,
    ``physmend.sweep.loop`` and ``from physmend.sweep import …`` are the subpackage as ever."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from physmend.api import functions

        return getattr(functions, self.__name__.rpartition(".")[2])(*args, **kwargs)


def _both(name: str) -> property:
    def get(self: types.ModuleType) -> Any:
        import importlib

        module = importlib.import_module(f"physmend.{name}")
        if not isinstance(module, _StageModule):
            module.__class__ = _StageModule
        return module

    def put(self: types.ModuleType, value: Any) -> None:  # the import system records the subpackage: ignored
        pass

    return property(get, put)


class _Physmend(types.ModuleType):
    """The ``physmend`` module: ``sweep`` and ``symbolic`` are both subpackage and stage function."""

    sweep = _both("sweep")
    symbolic = _both("symbolic")


sys.modules[__name__].__class__ = _Physmend


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'physmend' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, *_BOTH})
