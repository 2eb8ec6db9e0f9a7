"""physmend from Python: one function per stage and ``discover`` for all of them, typed results.

    import physmend
    d = physmend.discover("cstr", "cstr", discover={"n_trials": 1, "budget": None})
    d.formulas        # state -> sympy term added to its equation
    d.fit             # RMSE before/after per experiment and output (pandas)
    physmend.accept(d)

Every function composes the configuration exactly as the command line does (same checks, same
errors, same MLflow runs): see :mod:`physmend.api.functions`. Results: :mod:`physmend.api.results`.
"""

from __future__ import annotations

from physmend.api.discovery import Discovery
from physmend.api.functions import (
    accept,
    diagnose,
    discover,
    export,
    mask,
    propose,
    reject,
    sensitivity,
    sweep,
    symbolic,
)
from physmend.api.inputs import Dataset, Experiment
from physmend.api.results import (
    Decision,
    Diagnosis,
    ExportResult,
    MaskResult,
    Proposal,
    SensitivityResult,
    StageResult,
    SweepResult,
    SymbolicResult,
)

__all__ = [
    "Dataset",
    "Decision",
    "Diagnosis",
    "Discovery",
    "Experiment",
    "ExportResult",
    "MaskResult",
    "Proposal",
    "SensitivityResult",
    "StageResult",
    "SweepResult",
    "SymbolicResult",
    "accept",
    "diagnose",
    "discover",
    "export",
    "mask",
    "propose",
    "reject",
    "sensitivity",
    "sweep",
    "symbolic",
]
