"""The unit of a correction's fitted constant, from the term's unit and its variables' units.

A constant ``c`` that enters a term ``Δ`` (in the unit of its equation, e.g. ``N``) linearly —
``Δ = c·g(x) + h(x)`` with ``g`` and ``h`` free of ``c`` — carries ``unit(Δ) / unit(g)``: a drag
``c·v·|v|`` in ``N`` with ``v`` in ``m/s`` gives ``c`` in ``N/(m/s)^2``, i.e. ``kg/m``. A constant
inside a nonlinear function, a sum of constants or an unknown unit gives ``""`` (not known).
Units are written in SI base units (``kg.m-1``-style exponents shown as ``kg/m``), except words a
model declares of its own (``tu``, ``kanimals``), which stay words.
"""

from __future__ import annotations

from collections.abc import Mapping

import sympy as sp

from physmend.modeling.units import ANY, UnitMismatch, dimension, formula_dimension

#: base dimension -> its SI unit
_SI = {"M": "kg", "L": "m", "T": "s", "Θ": "K", "I": "A", "N": "mol", "J": "cd"}


def si_text(dim: Mapping[str, float]) -> str:
    """A dimension as an SI unit: ``{M: 1, L: -1}`` → ``kg/m``; ``1`` for a pure number."""
    def part(key: str, power: float) -> str:
        word = _SI.get(key, key)
        power = abs(power)
        return word if abs(power - 1) < 1e-9 else f"{word}^{power:g}"

    order = sorted(dim.items(), key=lambda kv: (list(_SI).index(kv[0]) if kv[0] in _SI else len(_SI), kv[0]))
    ups = [part(k, v) for k, v in order if v > 1e-9]
    downs = [part(k, v) for k, v in order if v < -1e-9]
    top = "·".join(ups) or "1"
    if not downs:
        return top
    return f"{top}/{downs[0]}" if len(downs) == 1 else f"{top}/({'·'.join(downs)})"


def constant_unit(term: sp.Expr, constant: sp.Symbol, term_unit: str, units: Mapping[str, str]) -> str:
    """The unit of ``constant`` in ``term`` (whose unit is ``term_unit``; ``units``: symbol name ->
    unit of the model's variables); ``""`` where it cannot be told (see the module)."""
    target = dimension(term_unit) if term_unit else None
    if target is None or constant not in term.free_symbols:
        return ""
    slope = sp.diff(term, constant)
    if constant in slope.free_symbols or slope == 0:
        return ""  # not linear in the constant
    known = {k: v for k, v in units.items() if v}
    try:
        dim = formula_dimension(slope, known)
    except UnitMismatch:
        return ""
    if dim is ANY:
        return ""  # another constant (or a variable without a unit) leaves it free
    assert isinstance(dim, dict)
    out = {k: target.get(k, 0.0) - dim.get(k, 0.0) for k in set(target) | set(dim)}
    return si_text({k: v for k, v in out.items() if abs(v) > 1e-9})
