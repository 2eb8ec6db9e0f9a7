"""A chosen formula's constants: named ``c1, c2 …`` (a value repeated up to its sign is one
constant) and multiplied out where its constants trade off against each other."""

from __future__ import annotations

import sympy as sp


def identifiable(expr: sp.Expr) -> sp.Expr:
    """``expr`` multiplied out where that leaves fewer fitted constants without growing it by more
    than half: a regression's ``c1·x·(c2·x + c3)`` is ``a·x² + b·x``, whose two constants the data
    can pin down (``c1`` and ``c2``, ``c3`` trade off against each other); otherwise ``expr``."""
    from physmend.modeling.evaluate import n_constants
    from physmend.symbolic.choice import tree_size

    try:
        expanded = sp.expand(expr)
    except Exception:  # noqa: BLE001 - a form sympy cannot multiply out stays as it is
        return expr
    if n_constants(expanded) < n_constants(expr) and tree_size(expanded) <= 1.5 * tree_size(expr):
        return expanded
    return expr


def name_constants(expr: sp.Expr, prefix: str = "c") -> tuple[sp.Expr, dict[str, float]]:
    """Replace the floating-point constants of ``expr`` by symbols ``c1, c2 …``; returns both.

    A value that appears again up to its sign is one constant (``-c·T⁴ + c·T_room⁴``: sympy expands
    ``c·(T⁴ − T_room⁴)``), written back as its common factor: ``c1·(T⁴ − T_room⁴)``."""
    consts: dict[str, float] = {}
    mapping: dict[sp.Basic, sp.Expr] = {}
    by_size: dict[float, sp.Symbol] = {}
    for f in sorted(expr.atoms(sp.Float), key=lambda a: (-abs(float(a)), float(a))):
        size = abs(float(f))
        if size in by_size:
            sym = by_size[size]
            mapping[f] = sym if float(f) == consts[sym.name] else -sym
            continue
        sym = sp.Symbol(f"{prefix}{len(by_size) + 1}")
        by_size[size] = sym
        mapping[f] = sym
        consts[sym.name] = float(f)
    named = expr.xreplace(mapping)
    if len(by_size) < len(mapping):
        named = sp.factor_terms(named)
    return named, consts
