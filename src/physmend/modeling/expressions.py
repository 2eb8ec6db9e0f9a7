"""Expressions as text in dotted model names (``c1*(zone1.air.T - zone2.air.T)``) <-> sympy."""

from __future__ import annotations

from collections.abc import Mapping

import sympy as sp

from physmend.modeling.safe_parse import parse_safe


def parse_expression(text: str, symbols: Mapping[str, sp.Symbol], *, where: str = "expression") -> sp.Expr:
    """Parse ``text`` whose variables are the keys of ``symbols`` (dotted names allowed) with the
    restricted parser (:mod:`physmend.modeling.safe_parse`: nothing in it is evaluated as Python).

    Raises :class:`ModelError` naming any variable that is not in ``symbols``, or what is not allowed.
    """
    return parse_safe(text, symbols, where=where)


def expression_text(expr: sp.Expr) -> str:
    """Readable text of ``expr`` that :func:`parse_expression` reads back."""
    return sp.sstr(expr)
