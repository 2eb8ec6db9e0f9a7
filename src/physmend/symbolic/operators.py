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
different back ends are comparable. An operator outside :data:`KNOWN`, a price that is not a whole
number ≥ 1, or an empty set is a one-line error naming the file and the entry.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import sympy as sp

# the operator names and their check live with the other configuration checks (the config layer)
from physmend.config_check import KNOWN, OperatorError, check_operators  # noqa: F401

#: the price of a function a formula may hold that is not among the operators (a catalogue form's)
UNLISTED_PRICE = 3

_OPERON = {"add": "add", "sub": "sub", "mul": "mul", "div": "div", "square": "square", "abs": "abs",
           "sqrt": "sqrtabs", "min": "fmin", "max": "fmax", "exp": "exp", "log": "logabs", "tanh": "tanh"}
_PYSR_BINARY = {"add": "+", "sub": "-", "mul": "*", "div": "/", "min": "min", "max": "max"}
_PYSR_UNARY = {"square": "square", "abs": "abs", "sqrt": "sqrt", "sign": "sign", "exp": "exp", "log": "log",
               "tanh": "tanh"}


def operon_symbols(ops: Mapping[str, int]) -> str:
    """pyoperon's ``allowed_symbols`` for ``ops`` (``sign`` has no pyoperon node: it is left to the
    catalogue and the other back ends)."""
    return ",".join(["constant", "variable", *[_OPERON[n] for n in ops if n in _OPERON]])


def pysr_operators(ops: Mapping[str, int]) -> dict[str, Any]:
    """PySR's ``binary_operators``, ``unary_operators`` and ``complexity_of_operators`` for ``ops``."""
    binary = [_PYSR_BINARY[n] for n in ops if n in _PYSR_BINARY]
    unary = [_PYSR_UNARY[n] for n in ops if n in _PYSR_UNARY]
    prices = {**{_PYSR_BINARY[n]: p for n, p in ops.items() if n in _PYSR_BINARY},
              **{_PYSR_UNARY[n]: p for n, p in ops.items() if n in _PYSR_UNARY}}
    return {"binary_operators": binary or ["+"], "unary_operators": unary, "complexity_of_operators": prices}


def priced_size(expr: sp.Expr, ops: Mapping[str, int]) -> int:
    """Complexity of ``expr``: one per variable and constant, plus each operator's price (an
    operator not in ``ops`` costs :data:`UNLISTED_PRICE`). ``sqrt(|a|)`` is one ``sqrt``; a factor
    ``b⁻¹`` is one ``div``; a negative coefficient is a ``sub``, not a product."""

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
            return size(base) + size(exp) + UNLISTED_PRICE
        names = {sp.Abs: "abs", sp.sign: "sign", sp.Min: "min", sp.Max: "max", sp.exp: "exp", sp.log: "log",
                 sp.tanh: "tanh"}
        for cls, name in names.items():
            if isinstance(e, cls):
                inner = e.args[0].args[0] if name == "log" and isinstance(e.args[0], sp.Abs) else None
                args = [inner] if inner is not None else list(e.args)
                return sum(size(a) for a in args) + price(name) * max(1, len(args) - 1)
        return sum(size(a) for a in e.args) + UNLISTED_PRICE

    return int(size(expr if isinstance(expr, sp.Basic) else sp.Float(expr)))
