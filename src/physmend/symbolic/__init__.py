"""Symbolic regression: formulas for a network's corrections, on a Pareto front.

One entry point over a string registry of back ends (``"operon"``, ``"sindy"``, ``"pysr"``)::

    from physmend.symbolic import fit, choose

    front = fit(X, y, ["zone1.air.T", "ambient.T"], units={"zone1.air.T": "K", "ambient.T": "K"},
                backend="sindy", target="zone1.air.T")
    i, why = choose(front)            # rule "knee"; or rule="best" / "bic", or index=N
    print(front.table()); print(why)
    front.candidates[i].expr          # sympy, in Symbols named like the inputs

Nothing heavy is imported until a back end runs (pyoperon ~1.2 s, pysindy ~1.3 s); PySR is
only imported where Julia is already installed.
"""

from __future__ import annotations

from physmend.symbolic._api import BACKENDS, available_backends, fit, fit_many, prepare
from physmend.symbolic._errors import BackendUnavailable, SymbolicError
from physmend.modeling.evaluate import display, evaluate, mse_r2
from physmend.symbolic._front import RULES, Candidate, ParetoFront, choose

__all__ = [
    "BACKENDS",
    "RULES",
    "BackendUnavailable",
    "Candidate",
    "ParetoFront",
    "SymbolicError",
    "available_backends",
    "choose",
    "display",
    "evaluate",
    "fit",
    "fit_many",
    "mse_r2",
    "prepare",
]
