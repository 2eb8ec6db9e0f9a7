"""Back end ``"sindy"``: sparse regression over physically motivated candidate terms.

The library is built generically from the inputs and their units (nothing about any one model):

- a constant, and each input ``u``;
- for every pair of inputs ``a, b`` with the same (known) unit, ``d = a - b``:
  ``d``, ``d·sqrt(|d|)``, ``d·|d|``, and ``a⁴ - b⁴`` when the unit is kelvin (``"K"``);
- each difference times each input whose unit is known and differs from the pair's: ``d·u``;
- with the operators ``sin``/``cos``: ``sin(u)``, ``cos(u)`` of each input that is an angle or a
  pure number by its unit (an angle in ``deg`` converted to radians).

Inputs without a unit are never paired. Regression is pysindy's sequentially thresholded least
squares (``STLSQ``) on unit-norm columns and a unit-norm target, so the threshold is a fraction of
the target's size; sweeping ``n_thresholds`` thresholds from ``threshold_min`` to
``threshold_max`` (log-spaced) gives models of decreasing size, one Pareto candidate per distinct
set of terms (complexity = number of terms).
"""

from __future__ import annotations

import importlib.util
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import sympy

from physmend.symbolic._api import resolve
from physmend.symbolic._errors import SymbolicError
from physmend.modeling.evaluate import abs_bars
from physmend.symbolic.operators import angle_scale, dimensionless, operators_for

DEFAULTS: dict[str, Any] = {
    "n_thresholds": 30,
    "threshold_min": 1e-4,
    "threshold_max": 1.0,
    "alpha": 1e-8,
    "max_iter": 30,
    "radiation_unit": "K",
    "products": True,
    "max_points": 20000,
}


@dataclass(frozen=True, eq=False)
class Term:
    """One library term: its sympy form in the input names and its values ``(n,)``."""

    expr: sympy.Expr
    values: np.ndarray

    @property
    def label(self) -> str:
        return str(self.expr)


def unavailable_reason() -> str | None:
    """Why this back end cannot run here, or None."""
    if importlib.util.find_spec("pysindy") is None:
        return "symbolic.backend=sindy needs pysindy, which is not installed: `pip install pysindy`, or use symbolic.backend=operon"
    return None


def prepare() -> None:
    """Import pysindy's optimiser (what :func:`search` uses)."""
    from pysindy.optimizers import STLSQ  # noqa: F401


def resolve_options(options: dict) -> dict[str, Any]:
    """Defaults updated by ``options`` (keys: see ``DEFAULTS``)."""
    settings = resolve(options, DEFAULTS, backend="sindy")
    lo, hi, k = settings["threshold_min"], settings["threshold_max"], settings["n_thresholds"]
    if not (isinstance(k, int) and k >= 1):
        raise SymbolicError(f"sindy option n_thresholds must be an integer >= 1, but got {k!r}")
    if not (0 < lo <= hi):
        raise SymbolicError(f"sindy options must satisfy 0 < threshold_min <= threshold_max, but got ({lo}, {hi})")
    return settings


#: the term families of the library before operators were data (``operators`` not given)
LEGACY = ("sub", "sqrt", "abs", "mul")


def library(X: np.ndarray, names: list[str], units: dict[str, str], *, radiation_unit: str = "K", products: bool = True,
            operators: Any = None) -> list[Term]:
    """Candidate terms for inputs ``X (n, k)`` named ``names`` with ``units`` (name -> unit string).

    ``operators`` (names, :mod:`physmend.symbolic.operators`) choose the families: ``sub`` the
    same-unit differences ``d``; with ``sqrt`` and ``mul`` ``d·sqrt(|d|)`` (and ``u·sqrt(|u|)``),
    with ``abs`` and ``mul`` ``d·|d|``, with ``mul`` the products ``d·u`` and ``u·v`` of any two
    inputs, with ``sign`` ``sign(u)`` and ``sign(d)``, with ``max``/``min`` the one-way parts
    ``max(d, 0)``/``min(d, 0)``, with ``sin``/``cos`` ``sin(u)``/``cos(u)`` of each input whose unit
    is an angle (in radians: ``sin(π/180·u)`` for ``deg``) or a pure number. ``pow`` (a fitted
    exponent) is not a linear family: pyoperon and PySR search it. None: the families before
    operators were data (no ``u·v``, no signed powers of single inputs)."""
    ops = set(LEGACY if operators is None else operators)
    legacy = operators is None
    n = X.shape[0]
    sym = [sympy.Symbol(s) for s in names]
    unit = [units.get(s) or None for s in names]
    terms = [Term(sympy.Integer(1), np.ones(n))]
    terms += [Term(sym[j], X[:, j]) for j in range(len(names))]
    if not legacy:
        for j in range(len(names)):
            for name, fn, f_np in (("sin", sympy.sin, np.sin), ("cos", sympy.cos, np.cos)):
                if name in ops and dimensionless(unit[j]):  # a phase: sin(u), with u in deg sin(π/180·u)
                    scale = angle_scale(unit[j]) or sympy.Integer(1)
                    terms.append(Term(fn(scale * sym[j]), f_np(float(scale) * X[:, j])))
            if "sqrt" in ops and "mul" in ops:
                terms.append(Term(sym[j] * sympy.sqrt(sympy.Abs(sym[j])), X[:, j] * np.sqrt(np.abs(X[:, j]))))
            if "sign" in ops:
                terms.append(Term(sympy.sign(sym[j]), np.sign(X[:, j])))
            if "mul" in ops and products:
                for m in range(j + 1, len(names)):
                    terms.append(Term(sym[j] * sym[m], X[:, j] * X[:, m]))
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if unit[i] is None or unit[i] != unit[j] or "sub" not in ops:
                continue
            d_expr = sym[i] - sym[j]
            d = X[:, i] - X[:, j]
            terms.append(Term(d_expr, d))
            if "sqrt" in ops and "mul" in ops:
                terms.append(Term(d_expr * sympy.sqrt(sympy.Abs(d_expr)), d * np.sqrt(np.abs(d))))
            if "abs" in ops and "mul" in ops:
                terms.append(Term(d_expr * sympy.Abs(d_expr), d * np.abs(d)))
            if unit[i] == radiation_unit:
                terms.append(Term(sym[i] ** 4 - sym[j] ** 4, X[:, i] ** 4 - X[:, j] ** 4))
            if "sign" in ops:
                terms.append(Term(sympy.sign(d_expr), np.sign(d)))
            if "max" in ops:
                terms.append(Term(sympy.Max(d_expr, 0), np.maximum(d, 0.0)))
            if "min" in ops:
                terms.append(Term(sympy.Min(d_expr, 0), np.minimum(d, 0.0)))
            if products and "mul" in ops:
                for m in range(len(names)):
                    if unit[m] is not None and unit[m] != unit[i]:
                        terms.append(Term(d_expr * sym[m], d * X[:, m]))
    return terms


def with_operators(settings: dict[str, Any], ops: dict[str, int], given: set[str]) -> dict[str, Any]:
    """The library's term families from the shared operators (:func:`library`)."""
    return {**settings, "operators": sorted(ops)}


def _text(pairs: list[tuple[Term, float]]) -> str:
    """``1.3*(a - b)*sqrt(|a - b|) - 0.2`` style text, 4 significant digits (display only)."""
    parts = []
    for term, c in pairs:
        mag = f"{abs(c):.4g}"
        label = abs_bars(term.label)
        if term.expr == 1:
            body = mag
        elif term.expr.is_Add:
            body = f"{mag}*({label})"
        else:
            body = f"{mag}*{label}"
        parts.append(("-" if c < 0 else "+", body))
    if not parts:
        return "0"
    text = ("-" if parts[0][0] == "-" else "") + parts[0][1]
    return text + "".join(f" {sign} {body}" for sign, body in parts[1:])


def search(
    X: np.ndarray, y: np.ndarray, names: list[str], *, units: dict[str, str], options: dict[str, Any], seed: int
) -> tuple[list[tuple[sympy.Expr, int, dict[str, float], str | None]], dict[str, Any]]:
    """Threshold sweep of STLSQ on ``X (n, k)``, ``y (n,)``; returns ``(expr, n_terms, terms, text)`` per model and the library."""
    from pysindy.optimizers import STLSQ

    ops = options.get("operators")
    if ops is not None:  # sin/cos only where an input is an angle (physmend.symbolic.operators.operators_for)
        ops = sorted(operators_for(dict.fromkeys(ops, 1), {n: units.get(n, "") for n in names}))
    terms = library(X, names, units, radiation_unit=options["radiation_unit"], products=options["products"],
                    operators=ops)
    norms = np.array([np.linalg.norm(t.values) for t in terms])
    keep = [i for i, t in enumerate(terms) if np.isfinite(t.values).all() and norms[i] > 0]
    terms = [terms[i] for i in keep]
    theta = np.column_stack([t.values for t in terms])
    y_norm = float(np.linalg.norm(y)) or 1.0
    y_scaled = y / y_norm

    seen: set[tuple[int, ...]] = set()
    out = []
    thresholds = np.geomspace(options["threshold_min"], options["threshold_max"], options["n_thresholds"])
    for threshold in thresholds:
        opt = STLSQ(threshold=float(threshold), alpha=options["alpha"], max_iter=options["max_iter"], normalize_columns=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            opt.fit(theta, y_scaled)
        w = np.asarray(opt.coef_, dtype=float).ravel() * y_norm
        support = tuple(int(i) for i in np.flatnonzero(w))
        if not support or support in seen or not np.isfinite(w).all():
            continue
        seen.add(support)
        coef = {terms[i].label: float(w[i]) for i in support}
        expr = sympy.Add(*[sympy.Float(w[i]) * terms[i].expr for i in support])
        out.append((expr, len(support), coef, _text([(terms[i], float(w[i])) for i in support])))
    if not out:  # the target is zero (or no term survives any threshold): the empty model
        out.append((sympy.Integer(0), 0, {}, "0"))
    return out, {"library": [t.label for t in terms]}
