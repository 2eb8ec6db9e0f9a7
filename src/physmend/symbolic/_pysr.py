"""Back end ``"pysr"``: PySR (genetic programming in Julia), only where Julia is already installed.

``import pysr`` downloads Julia when it finds none, and can wait on the network. This module
therefore checks, without importing pysr, that the package is installed and that a Julia
executable exists (``julia`` on PATH, ``PYTHON_JULIAPKG_EXE``, ``PYTHON_JULIACALL_BINDIR`` or a
Julia installed earlier by juliapkg in this environment). Before importing pysr it sets
``PYTHON_JULIAPKG_OFFLINE=yes`` (unless the user set it) so that nothing is ever downloaded:
PySR's Julia packages must have been installed beforehand (run ``python -c "import pysr"`` once
with network access).

This back end is not exercised by the test suite (no Julia here); its settings are deliberately
small and conservative.
"""

from __future__ import annotations

import importlib.util
import inspect
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from physmend.symbolic._api import resolve
from physmend.symbolic._errors import BackendUnavailable, SymbolicError

UNAVAILABLE = (
    "symbolic.backend=pysr needs PySR and a Julia installation (julia on PATH); none was found. "
    "Install Julia and `pip install physmend[pysr]`, or use symbolic.backend=operon"
)

DEFAULTS: dict[str, Any] = {
    "niterations": 40,
    "populations": 8,
    "population_size": 50,
    "maxsize": 25,
    "binary_operators": ["+", "-", "*", "/"],
    "unary_operators": ["sqrt", "abs", "square"],
    "timeout_in_seconds": 300,
    "max_points": 2000,
}


#: settings key holding the shared operators and the keys made from them until :func:`search` knows
#: the inputs' units (never passed to PySR)
SHARED = "shared_operators"


def with_operators(settings: dict[str, Any], ops: dict[str, int], given: set[str]) -> dict[str, Any]:
    """``binary_operators``, ``unary_operators`` and ``complexity_of_operators`` (with ``pow`` also
    ``extra_sympy_mappings`` and ``constraints``) from the shared operators
    (:mod:`physmend.symbolic.operators`), each unless given as a back-end option; :func:`search`
    keeps ``sin``/``cos`` only where an input is an angle (``operators_for``)."""
    from physmend.symbolic.operators import pysr_operators

    made = {k: v for k, v in pysr_operators(ops).items() if k not in given}
    return {**settings, **made, SHARED: (dict(ops), sorted(made))}


def operator_settings(options: dict[str, Any], names: list[str], units: dict[str, str]) -> dict[str, Any]:
    """``options`` less physmend's own keys, the operator settings made from the shared operators
    (:func:`with_operators`) made again for inputs ``names`` with ``units`` (``sin``/``cos`` only
    where one is an angle: :func:`physmend.symbolic.operators.operators_for`)."""
    settings = {k: v for k, v in options.items() if k not in ("max_points", SHARED)}
    if options.get(SHARED) is not None:
        from physmend.symbolic.operators import operators_for, pysr_operators

        ops, made = options[SHARED]
        fitted = pysr_operators(operators_for(ops, {n: units.get(n, "") for n in names}))
        for key in made:
            settings.pop(key, None)
            if key in fitted:
                settings[key] = fitted[key]
    return settings


def _julia_executable() -> str | None:
    """A Julia executable that exists on this machine, or None (nothing is imported or started)."""
    candidates = [shutil.which("julia"), os.environ.get("PYTHON_JULIAPKG_EXE")]
    bindir = os.environ.get("PYTHON_JULIACALL_BINDIR")
    if bindir:
        candidates.append(str(Path(bindir) / "julia"))
    candidates.append(str(Path(sys.prefix) / "julia_env" / "pyjuliapkg" / "install" / "bin" / "julia"))
    for exe in candidates:
        if exe and Path(exe).is_file() and os.access(exe, os.X_OK):
            return exe
    return None


def unavailable_reason() -> str | None:
    """Why this back end cannot run here, or None; never imports pysr."""
    if importlib.util.find_spec("pysr") is None or _julia_executable() is None:
        return UNAVAILABLE
    return None


def resolve_options(options: dict) -> dict[str, Any]:
    """Defaults updated by ``options``; keys of ``DEFAULTS`` only (PySR is imported later)."""
    return resolve(options, DEFAULTS, backend="pysr")


def search(
    X: np.ndarray, y: np.ndarray, names: list[str], *, units: dict[str, str], options: dict[str, Any], seed: int
) -> tuple[list[tuple[sympy.Expr, int, dict[str, float], str | None]], dict[str, Any]]:
    """Run PySR on ``X (n, k)``, ``y (n,)``; returns ``(expr, PySR complexity, {}, None)`` per hall-of-fame entry."""
    exe = _julia_executable()
    if exe is None or importlib.util.find_spec("pysr") is None:
        raise BackendUnavailable(UNAVAILABLE)
    os.environ.setdefault("PYTHON_JULIAPKG_OFFLINE", "yes")
    os.environ.setdefault("PYTHON_JULIAPKG_EXE", exe)
    try:
        from pysr import PySRRegressor
    except Exception as exc:  # Julia packages missing, offline resolution failed, ...
        raise BackendUnavailable(f"{UNAVAILABLE} (importing pysr failed: {exc})") from exc

    settings = operator_settings(options, names, units)
    settings.update(
        model_selection="best",
        random_state=int(seed),
        deterministic=True,
        parallelism="serial",
        progress=False,
        verbosity=0,
    )
    accepted = set(inspect.signature(PySRRegressor.__init__).parameters)
    tmp = tempfile.mkdtemp(prefix="physmend-pysr-")
    for key, value in (("output_directory", tmp), ("temp_equation_file", True), ("tempdir", tmp)):
        if key in accepted:
            settings[key] = value
    settings = {k: v for k, v in settings.items() if k in accepted}
    stand_ins = [f"x{i}" for i in range(len(names))]
    model = PySRRegressor(**settings)
    model.fit(X, y, variable_names=stand_ins)

    from physmend.modeling.safe_parse import parse_safe

    by_name = {f"x{i}": sympy.Symbol(name) for i, name in enumerate(names)}
    out = []
    for _, row in model.equations_.iterrows():
        expr = parse_safe(str(row["sympy_format"]), where="PySR formula", new_symbols=True)
        expr = expr.xreplace({s: by_name[s.name] for s in expr.free_symbols if s.name in by_name})
        unknown = [s.name for s in expr.free_symbols if s.name not in names]
        if unknown:
            raise SymbolicError(f"PySR returned a formula in unknown variables {unknown}: {row['sympy_format']}")
        out.append((expr, int(row["complexity"]), {}, None))
    return out, {}
