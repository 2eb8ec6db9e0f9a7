"""Numbers from sympy expressions: evaluation on named data columns, fit scores, display.

Expressions are sympy expressions whose free symbols are named exactly like the data columns
(dotted names such as ``"zone1.air.T"`` are fine); they are evaluated with numpy on named
columns ``name -> (n,)`` arrays.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import sympy

from physmend.modeling.errors import ModelError


def evaluate(expr: sympy.Expr, columns: Mapping[str, np.ndarray], *, n: int | None = None) -> np.ndarray:
    """Evaluate ``expr`` on named columns; returns a float64 array of shape ``(n,)``.

    Args:
        expr: sympy expression; every free symbol's name must be a key of ``columns``.
        columns: variable name -> values, each ``(n,)`` (or a scalar, broadcast).
        n: number of points; defaults to the length of the first non-scalar column.

    Raises:
        ModelError: a symbol of ``expr`` has no column.
    """
    symbols = sorted(expr.free_symbols, key=lambda s: s.name)
    missing = [s.name for s in symbols if s.name not in columns]
    if missing:
        raise ModelError(
            f"every variable of the expression must have values, but none were given for {missing} "
            f"(given: {sorted(columns)})"
        )
    if n is None:
        sizes = [np.size(v) for v in columns.values() if np.ndim(v) > 0]
        n = sizes[0] if sizes else 1
    # Symbols with dots are not Python identifiers: evaluate through safe stand-ins.
    dummies = [sympy.Symbol(f"_v{i}") for i in range(len(symbols))]
    f = sympy.lambdify(dummies, expr.xreplace(dict(zip(symbols, dummies))), modules=["scipy", "numpy"])
    with np.errstate(all="ignore"):
        out = f(*[np.asarray(columns[s.name], dtype=float) for s in symbols])
    out = np.asarray(out, dtype=float)
    return np.array(np.broadcast_to(out, (n,)), dtype=float)


def mse_r2(y: np.ndarray, y_hat: np.ndarray) -> tuple[float, float]:
    """Mean squared error (target units²) and coefficient of determination of ``y_hat`` for ``y``.

    R² is ``1 - SS_res / SS_tot``. For a (numerically) constant target, ``SS_tot`` is replaced by
    ``sum(y²)`` (uncentered R²); for an all-zero target R² is 1 for an exact fit and 0 otherwise.
    """
    y = np.asarray(y, dtype=float)
    r = np.asarray(y_hat, dtype=float) - y
    ss_res = float(np.sum(r * r))
    ss_tot = float(np.sum((y - np.mean(y)) ** 2))
    ss_raw = float(np.sum(y * y))
    mse = ss_res / y.size
    if ss_tot <= 1e-12 * ss_raw:
        ss_tot = ss_raw
    if ss_tot > 0:
        r2 = 1.0 - ss_res / ss_tot
    else:
        r2 = 1.0 if ss_res == 0 else 0.0
    return mse, r2


def round_floats(expr: sympy.Expr, digits: int = 4) -> sympy.Expr:
    """``expr`` with every floating-point constant rounded to ``digits`` significant digits (display only)."""
    repl = {f: sympy.Float(float(f"{float(f):.{digits}g}"), digits) for f in expr.atoms(sympy.Float)}
    return expr.xreplace(repl)


def display(expr: sympy.Expr, digits: int = 4) -> str:
    """Readable one-line text of ``expr``: constants to ``digits`` significant digits, ``|x|`` for Abs."""
    text = str(round_floats(expr, digits))
    return abs_bars(text)


def abs_bars(text: str) -> str:
    """Rewrite ``Abs(...)`` as ``|...|`` (balanced parentheses)."""
    out = []
    i = 0
    while i < len(text):
        if text.startswith("Abs(", i):
            depth, j = 1, i + 4
            while j < len(text) and depth:
                depth += {"(": 1, ")": -1}.get(text[j], 0)
                j += 1
            out.append("|" + abs_bars(text[i + 4 : j - 1]) + "|")
            i = j
        else:
            out.append(text[i])
            i += 1
    return "".join(out)


def n_constants(expr: sympy.Expr) -> int:
    """Number of fitted (floating-point) constants in ``expr``; at least 1. A value that appears
    again, up to its sign, is one constant (``-c·T⁴ + c·T_room⁴`` has one: ``c·(T⁴ − T_room⁴)``
    expanded)."""
    return max(1, len({abs(float(f)) for f in expr.atoms(sympy.Float)}))
