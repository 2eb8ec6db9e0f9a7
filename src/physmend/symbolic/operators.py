"""The operators formulas may use, as data (the ``operators`` config group), shared by every back end.

A config file maps operator names to their complexity price (a whole number ≥ 1)::

    add: 1
    mul: 1
    sqrt: 1      # sqrt(|x|): with mul, the signed powers x·|x|^½
    sign: 2

Each back end searches with the operators it can write (:func:`operon_symbols`,
:func:`pysr_operators`, the sparse library's term families in :mod:`physmend.symbolic._sindy`), and
every candidate of every back end (and of the mechanism catalogue) is priced by one rule,
:func:`priced_size`: one per variable and constant plus each operator's price, so fronts from
different back ends are comparable. An operator outside :data:`physmend.config_check.KNOWN`, a price that is not a whole
number ≥ 1, or an empty set is a one-line error naming the file and the entry.

The trigonometric operators ``sin`` and ``cos`` are periodic: their argument is a phase, an angle.
:func:`operators_for` keeps them exactly where some candidate input is an angle by its declared unit
(``rad``, ``deg``, :data:`ANGLE_UNITS`) and leaves them out otherwise, so a set that lists them
searches with them only on problems that have an angle; the symbolic stage applies it to the
configured set before any back end searches.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import sympy as sp

#: the price of a function a formula may hold that is not among the operators (a catalogue form's)
UNLISTED_PRICE = 3

#: operators whose argument must be a phase (an angle): kept by :func:`operators_for` only where an input is one
TRIGONOMETRIC = ("sin", "cos")

#: declared units of an angle -> radians per unit (``sin`` of an input in ``deg`` is ``sin(π/180·u)``)
ANGLE_UNITS: dict[str, sp.Expr] = {"rad": sp.Integer(1), "deg": sp.pi / 180, "degree": sp.pi / 180,
                                   "°": sp.pi / 180, "rev": 2 * sp.pi}

_OPERON = {"add": "add", "sub": "sub", "mul": "mul", "div": "div", "square": "square", "abs": "abs",
           "sqrt": "sqrtabs", "min": "fmin", "max": "fmax", "exp": "exp", "log": "logabs", "tanh": "tanh",
           "sin": "sin", "cos": "cos", "pow": "powabs"}
_PYSR_BINARY = {"add": "+", "sub": "-", "mul": "*", "div": "/", "min": "min", "max": "max",
                "pow": "powabs(x, y) = abs(x)^y"}
_PYSR_UNARY = {"square": "square", "abs": "abs", "sqrt": "sqrt", "sign": "sign", "exp": "exp", "log": "log",
               "tanh": "tanh", "sin": "sin", "cos": "cos"}


def _pysr_name(operator: str) -> str:
    """The name PySR knows an operator by (a custom Julia definition ``f(x, y) = …`` by ``f``)."""
    return operator.split("(", 1)[0].strip()


def angle_scale(unit: str | None) -> sp.Expr | None:
    """Radians per unit where ``unit`` declares an angle (:data:`ANGLE_UNITS`), else None."""
    return ANGLE_UNITS.get((unit or "").strip())


def dimensionless(unit: str | None) -> bool:
    """Whether ``unit`` declares an angle or a pure number (``"1"``, ``"%"``): a quantity ``sin`` and
    ``cos`` may take as it is. An empty (unknown) unit is not."""
    if angle_scale(unit) is not None:
        return True
    from physmend.modeling.units import dimension

    return dimension(unit) == {}


def operators_for(ops: Mapping[str, Any], units: Mapping[str, str]) -> dict[str, Any]:
    """``ops`` for a search whose candidate inputs have ``units`` (name -> declared unit).

    The trigonometric operators (:data:`TRIGONOMETRIC`) are periodic, so their argument is a phase:
    they stay where some input is an angle by its declared unit (:data:`ANGLE_UNITS`: ``rad``,
    ``deg`` …) and are left out otherwise. A unit-free ratio (a state of charge, an efficiency,
    ``"1"``) is no phase and does not bring them in (declare an angle ``rad``). Every other entry,
    prices and switched-off entries (``None``) included, is returned as given, so a problem without
    an angle searches with exactly the configured set less ``sin`` and ``cos``.
    """
    if any(angle_scale(u) is not None for u in units.values()):
        return dict(ops)
    return {name: price for name, price in ops.items() if str(name) not in TRIGONOMETRIC}


def operon_symbols(ops: Mapping[str, int]) -> str:
    """pyoperon's ``allowed_symbols`` for ``ops`` (``sign`` has no pyoperon node: it is left to the
    catalogue and the other back ends; ``pow`` is pyoperon's ``powabs``, ``|a|^b``)."""
    return ",".join(["constant", "variable", *[_OPERON[n] for n in ops if n in _OPERON]])


def pysr_operators(ops: Mapping[str, int]) -> dict[str, Any]:
    """PySR's ``binary_operators``, ``unary_operators`` and ``complexity_of_operators`` for ``ops``;
    with ``pow`` the custom operator ``powabs(x, y) = abs(x)^y`` whose exponent is held to one node
    (a fitted constant or a variable: ``constraints``) and its sympy meaning (``extra_sympy_mappings``)."""
    binary = [_PYSR_BINARY[n] for n in ops if n in _PYSR_BINARY]
    unary = [_PYSR_UNARY[n] for n in ops if n in _PYSR_UNARY]
    prices = {**{_pysr_name(_PYSR_BINARY[n]): p for n, p in ops.items() if n in _PYSR_BINARY},
              **{_PYSR_UNARY[n]: p for n, p in ops.items() if n in _PYSR_UNARY}}
    out: dict[str, Any] = {"binary_operators": binary or ["+"], "unary_operators": unary,
                           "complexity_of_operators": prices}
    if "pow" in ops:
        out["extra_sympy_mappings"] = {"powabs": lambda a, b: sp.Abs(a) ** b}
        out["constraints"] = {"powabs": (-1, 1)}
    return out


def priced_size(expr: sp.Expr, ops: Mapping[str, int]) -> int:
    """Complexity of ``expr``: one per variable and constant, plus each operator's price (an
    operator not in ``ops`` costs :data:`UNLISTED_PRICE`). ``sqrt(|a|)`` is one ``sqrt``; a factor
    ``b⁻¹`` is one ``div``; a negative coefficient is a ``sub``, not a product; with ``pow`` in
    ``ops`` any other power ``|a|^c`` (or ``a^c``) is one ``pow`` plus its base and exponent (without
    it, the power and its ``|·|`` cost as before: base, exponent and :data:`UNLISTED_PRICE`)."""

    def price(name: str) -> int:
        return int(ops.get(name, UNLISTED_PRICE))

    def size(e: sp.Expr) -> int:
        if e.is_Atom:
            return 1
        if e.is_Add:  # a - b is Add(a, Mul(-1, b)) in sympy: priced as one subtraction
            total = 0
            for i, a in enumerate(e.args):
                negated = a.is_Mul and a.args and a.args[0] == -1
                body = sp.Mul(*a.args[1:]) if negated else a
                total += size(body) + (price("sub") if negated else (price("add") if i else 0))
            return total
        if e.is_Mul:
            args = list(e.args)
            if args and args[0] == -1:  # -x: a subtraction, priced as one
                args = args[1:]
                extra = price("sub")
            else:
                extra = 0
            total = extra
            for i, a in enumerate(args):
                if a.is_Pow and a.exp == -1:
                    total += size(a.base) + (price("div") if i else price("div") + 1)  # 1/b alone: 1 / b
                else:
                    total += size(a) + (price("mul") if i else 0)
            return total
        if e.is_Pow:
            base, exp = e.args
            if exp == 2:
                return size(base) + price("square")
            if exp == sp.Rational(1, 2):
                inner = base.args[0] if isinstance(base, sp.Abs) else base
                return size(inner) + price("sqrt")
            if exp == -1:
                return size(base) + price("div") + 1
            if "pow" in ops:  # |a|^c is one power node (pyoperon's powabs), as sqrt(|a|) is one sqrt
                inner = base.args[0] if isinstance(base, sp.Abs) else base
                return size(inner) + size(exp) + price("pow")
            return size(base) + size(exp) + UNLISTED_PRICE
        names = {sp.Abs: "abs", sp.sign: "sign", sp.Min: "min", sp.Max: "max", sp.exp: "exp", sp.log: "log",
                 sp.tanh: "tanh", sp.sin: "sin", sp.cos: "cos"}
        for cls, name in names.items():
            if isinstance(e, cls):
                inner = e.args[0].args[0] if name == "log" and isinstance(e.args[0], sp.Abs) else None
                args = [inner] if inner is not None else list(e.args)
                return sum(size(a) for a in args) + price(name) * max(1, len(args) - 1)
        return sum(size(a) for a in e.args) + UNLISTED_PRICE

    return int(size(expr if isinstance(expr, sp.Basic) else sp.Float(expr)))
