"""The parts a model is made of: variables, equations as written, measured outputs.

Plain frozen dataclasses with no behaviour beyond printing; :mod:`physmend.modeling.model` builds
them and :mod:`physmend.modeling.simplify` reads them, through :class:`Declared` (what a model
offers of them), so that simplification need not know the model class.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import sympy as sp

Kind = Literal["state", "parameter", "input", "algebraic"]

@dataclass(frozen=True)
class Variable:
    """One named quantity of a model.

    ``start`` (states only) may be a number or a sympy expression of parameters.
    ``value``, ``uncertain`` and ``bounds`` apply to parameters only.
    """

    name: str
    kind: Kind
    symbol: sp.Symbol
    unit: str = ""
    description: str = ""
    start: sp.Expr | None = None
    value: float | None = None
    uncertain: bool = False
    bounds: tuple[float, float] | None = None


@dataclass(frozen=True)
class Equation:
    """``lhs = rhs`` as written by the user; ``owner`` is the component it belongs to."""

    lhs: sp.Expr
    rhs: sp.Expr
    owner: str = ""
    label: str = ""

    @property
    def residual(self) -> sp.Expr:
        return self.lhs - self.rhs

    def __str__(self) -> str:
        text = f"{sp.sstr(self.lhs)} = {sp.sstr(self.rhs)}"
        where = self.label or self.owner
        return f"[{where}] {text}" if where else text


@dataclass(frozen=True)
class Output:
    """A measured output ``name = expr``; ``name`` is the telemetry channel it is compared to."""

    name: str
    expr: sp.Expr
    unit: str = ""
    description: str = ""


def der_name(state_name: str) -> str:
    return f"der({state_name})"


class Declared(Protocol):
    """A model as its declarations: what structural simplification reads (a
    :class:`physmend.modeling.model.Model` is one)."""

    name: str
    variables: dict[str, Variable]
    equations: list[Equation]
    outputs: dict[str, Output]

    def of_kind(self, kind: Kind) -> list[Variable]: ...

    def connection_equations(self) -> list[Equation]: ...
