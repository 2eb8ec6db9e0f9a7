"""Expressions as text in dotted model names (``c1*(zone1.air.T - zone2.air.T)``) <-> sympy."""

from __future__ import annotations

import re
from collections.abc import Mapping

import sympy as sp

from physmend.modeling.errors import ModelError

_DOTTED = re.compile(r"(?<![\w.])([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)")


def parse_expression(text: str, symbols: Mapping[str, sp.Symbol], *, where: str = "expression") -> sp.Expr:
    """Parse ``text`` whose variables are the keys of ``symbols`` (dotted names allowed).

    Raises :class:`ModelError` naming any variable that is not in ``symbols``.
    """
    tokens: dict[str, sp.Symbol] = {}

    def repl(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in symbols:
            raise ModelError(f"{where}: uses {name!r}, which is not a known variable or constant")
        token = f"_v{len(tokens)}_"
        tokens[token] = symbols[name]
        return token

    plain = _DOTTED.sub(repl, text)
    local = {**{k: v for k, v in symbols.items() if "." not in k}, **tokens}
    try:
        expr = sp.sympify(plain, locals=local)
    except (sp.SympifyError, SyntaxError, TypeError, AttributeError) as exc:
        raise ModelError(f"{where}: {text!r} is not a valid expression ({exc})") from None
    unknown = sorted(s.name for s in expr.free_symbols if s not in set(local.values()))
    if unknown:
        raise ModelError(f"{where}: uses {unknown[0]!r}, which is not a known variable or constant")
    return expr


def expression_text(expr: sp.Expr) -> str:
    """Readable text of ``expr`` that :func:`parse_expression` reads back."""
    return sp.sstr(expr)
