"""Back end ``"operon"``: multi-objective genetic programming with pyoperon (accuracy and tree length).

pyoperon's ``SymbolicRegressor`` with objectives ``["r2", "length"]`` runs NSGA-II; its final
non-dominated set is the Pareto front. Model strings are written with stand-in names ``x0..x{k-1}``
(full precision: 20 decimals) and parsed with sympy into Symbols named like the inputs.

Default settings (measured on 2 cores, 2,000 points, 3 inputs: 2–7 s):
population 300, 50 generations, trees of at most 25 nodes and depth 8, 5 Levenberg–Marquardt
steps on the constants of each offspring, operators ``add, sub, mul, div, square, abs, sqrtabs``
(``sqrtabs(x) = sqrt(|x|)``, so ``c·ΔT·sqrt(|ΔT|)`` is a tree of length 12). With the shared
operators (the ``operators`` config group) the symbols are theirs: ``sin``/``cos`` where an input is
an angle, ``pow`` as ``powabs`` (``|a|^b``, written ``abs(a) ^ b``).
"""

from __future__ import annotations

import importlib.util
import inspect
import warnings
from typing import Any

import numpy as np
import sympy

from physmend.symbolic._api import resolve
from physmend.symbolic._errors import SymbolicError

DEFAULTS: dict[str, Any] = {
    "allowed_symbols": "add,sub,mul,div,constant,variable,square,abs,sqrtabs",
    "objectives": ["r2", "length"],
    "population_size": 300,
    "generations": 50,
    "max_length": 25,
    "max_depth": 8,
    "optimizer_iterations": 5,
    "tournament_size": 3,
    "max_evaluations": 1_000_000,
    "max_time": 60,
    "n_threads": 1,  # one thread: the same seed gives the same front (parallel evolution is not reproducible)
    "max_points": 2000,
}

# sympy meanings of the function names pyoperon's infix formatter can write.
_FUNCTIONS: dict[str, Any] = {
    "abs": sympy.Abs,
    "sqrt": sympy.sqrt,
    "sqrtabs": lambda x: sympy.sqrt(sympy.Abs(x)),
    "square": lambda x: x**2,
    "cbrt": sympy.cbrt,
    "exp": sympy.exp,
    "log": sympy.log,
    "logabs": lambda x: sympy.log(sympy.Abs(x)),
    "log1p": lambda x: sympy.log(1 + x),
    "sin": sympy.sin,
    "cos": sympy.cos,
    "tan": sympy.tan,
    "asin": sympy.asin,
    "acos": sympy.acos,
    "atan": sympy.atan,
    "sinh": sympy.sinh,
    "cosh": sympy.cosh,
    "tanh": sympy.tanh,
    "fmin": sympy.Min,
    "fmax": sympy.Max,
    "aq": lambda a, b: a / sympy.sqrt(1 + b**2),
    "powabs": lambda a, b: sympy.Abs(a) ** b,
    "pow": lambda a, b: a**b,
    "floor": sympy.floor,
    "ceil": sympy.ceiling,
}


def unavailable_reason() -> str | None:
    """Why this back end cannot run here, or None."""
    missing = [m for m in ("pyoperon", "sklearn") if importlib.util.find_spec(m) is None]
    if missing:
        return (
            f"symbolic.backend=operon needs {' and '.join(missing)}, which {'is' if len(missing) == 1 else 'are'} "
            "not installed: `pip install pyoperon scikit-learn`, or use symbolic.backend=sindy"
        )
    return None


def prepare() -> None:
    """Import pyoperon's regressor (what :func:`resolve_options` and :func:`search` use)."""
    from pyoperon.sklearn import SymbolicRegressor  # noqa: F401


def resolve_options(options: dict) -> dict[str, Any]:
    """Defaults updated by ``options``; any ``pyoperon.sklearn.SymbolicRegressor`` argument is accepted."""
    from pyoperon.sklearn import SymbolicRegressor

    passthrough = frozenset(inspect.signature(SymbolicRegressor.__init__).parameters) - {"self", "random_state"}
    return resolve(options, DEFAULTS, backend="operon", extra=passthrough)


#: settings key holding the shared operators until :func:`search` knows the inputs' units (not pyoperon's)
SHARED = "shared_operators"


def with_operators(settings: dict[str, Any], ops: dict[str, int], given: set[str]) -> dict[str, Any]:
    """``allowed_symbols`` from the shared operators (:mod:`physmend.symbolic.operators`) unless the
    back end's own ``allowed_symbols`` option was given; :func:`search` keeps ``sin``/``cos`` only
    where an input is an angle (:func:`physmend.symbolic.operators.operators_for`)."""
    from physmend.symbolic.operators import operon_symbols

    if "allowed_symbols" in given:
        return settings
    return {**settings, "allowed_symbols": operon_symbols(ops), SHARED: dict(ops)}


def operator_settings(options: dict[str, Any], names: list[str], units: dict[str, str]) -> dict[str, Any]:
    """``options`` less physmend's own keys, with ``allowed_symbols`` made from the shared operators
    (:func:`with_operators`) for inputs ``names`` with ``units`` (``sin``/``cos`` only where one is an
    angle: :func:`physmend.symbolic.operators.operators_for`)."""
    settings = {k: v for k, v in options.items() if k not in ("max_points", SHARED)}
    if options.get(SHARED) is not None:
        from physmend.symbolic.operators import operators_for, operon_symbols

        settings["allowed_symbols"] = operon_symbols(operators_for(options[SHARED], {n: units.get(n, "") for n in names}))
    return settings


def parse_model(text: str, names: list[str]) -> sympy.Expr:
    """Parse a pyoperon infix string written with stand-ins ``x0..`` into an expression in ``names``."""
    from physmend.modeling.errors import ModelError
    from physmend.modeling.safe_parse import parse_safe

    local = {f"x{i}": sympy.Symbol(name) for i, name in enumerate(names)}
    try:
        return parse_safe(text, local, where="pyoperon model")  # restricted: nothing is evaluated as Python
    except ModelError as exc:
        raise SymbolicError(f"could not parse the pyoperon model {text!r} ({exc})") from exc


def search(
    X: np.ndarray, y: np.ndarray, names: list[str], *, units: dict[str, str], options: dict[str, Any], seed: int
) -> tuple[list[tuple[sympy.Expr, int, dict[str, float], str | None]], dict[str, Any]]:
    """Run pyoperon on ``X (n, k)``, ``y (n,)``; returns ``(expr, tree length, {}, None)`` per front member and run details."""
    return read_front(regress(X, y, names, units=units, options=options, seed=seed), names)


def regress(X: np.ndarray, y: np.ndarray, names: list[str], *, units: dict[str, str], options: dict[str, Any],
            seed: int) -> tuple[Any, dict[str, Any]]:
    """The evolution alone: pyoperon's fitted ``SymbolicRegressor`` on ``X (n, k)``, ``y (n,)`` and its
    settings. It holds no interpreter lock while it evolves, and touches no state of this process:
    several may run side by side in threads (:func:`physmend.symbolic.fit_many`)."""
    from pyoperon.sklearn import SymbolicRegressor

    settings = operator_settings(options, names, units)
    try:
        reg = SymbolicRegressor(random_state=int(seed) % 2**63, **settings)
        reg.fit(X, y)
    except ValueError as exc:
        raise SymbolicError(f"pyoperon refused the settings {settings} ({exc})") from exc
    return reg, settings


def read_front(fitted: tuple[Any, dict[str, Any]], names: list[str]
               ) -> tuple[list[tuple[sympy.Expr, int, dict[str, float], str | None]], dict[str, Any]]:
    """:func:`search`'s result from a :func:`regress` result (in the calling thread: it changes the
    warning filters for a moment)."""
    reg, settings = fitted
    stand_ins = [f"x{i}" for i in range(len(names))]
    out = []
    for member in reg.pareto_front_:
        with warnings.catch_warnings():  # "Model contains no variables" for a constant: fine here
            warnings.simplefilter("ignore")
            text = reg.get_model_string(member["tree"], 20, names=stand_ins)
        out.append((parse_model(text, names), int(member["length"]), {}, None))
    return out, {"generations": int(reg.stats_.get("generations", 0)), "allowed_symbols": settings.get("allowed_symbols")}
