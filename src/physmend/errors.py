"""Errors that mean "your input is wrong" (reported as one message, no traceback) — and only those.

They are named here, not imported: their modules import torch, pandas, sympy and MLflow (2 s of a
command's start), and an error raised before any of those loaded (a store that cannot be opened, a
bad override) is reported at once. :func:`is_user_error` compares a raised error's classes by module
and name: an error can be an instance of one of these classes only once its module is loaded, so the
answer is that of ``isinstance(exc, USER_ERRORS)``.
"""

from __future__ import annotations

import importlib
from typing import Any

#: (module, class) of every error that means "your input is wrong"
USER_ERROR_NAMES: tuple[tuple[str, str], ...] = (
    ("physmend.ude.stored_spec", "ArtifactError"),
    ("physmend.config", "ConfigError"),
    ("physmend.data.errors", "DataError"),
    ("physmend.explain.catalogue", "MechanismError"),
    ("physmend.modeling.errors", "ModelError"),
    ("physmend.settings.shipped", "SettingError"),
    ("physmend.sweep.run", "NoTrialCompleted"),
    ("physmend.simulate.errors", "SimulationError"),
    ("physmend.symbolic._errors", "SymbolicError"),
    ("physmend.tracking.store", "TrackingError"),
    ("physmend.ude.outcome", "TrainingDiverged"),
    ("physmend.ude.hybrid", "UDEConfigError"),
)


def is_user_error(exc: BaseException) -> bool:
    """Whether ``exc`` is one of the user errors (or a subclass of one), without importing any."""
    return any((cls.__module__, cls.__qualname__) in USER_ERROR_NAMES for cls in type(exc).__mro__)


def user_errors() -> tuple[type[Exception], ...]:
    """The user error classes themselves (imports every module that defines one: seconds)."""
    return tuple(getattr(importlib.import_module(module), name) for module, name in USER_ERROR_NAMES)


def __getattr__(name: str) -> Any:
    if name == "USER_ERRORS":  # the tuple, for ``except USER_ERRORS``: built on first use
        return user_errors()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
