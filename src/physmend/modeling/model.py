"""The symbolic model a user writes: states, parameters, inputs, algebraic variables, equations, outputs.

A model is a semi-explicit DAE written with sympy. Every variable has a hierarchical name
(``zone2.air.T``); derivatives are written ``model.der(T)``. Equations are kept as written, each
with the component (``owner``) it belongs to, so that later stages can attach corrections to the
equation of the component where they act.

Example::

    m = Model("tank")
    h = m.state("tank.h", start=1.0, unit="m", description="level")
    q = m.variable("tank.q_out", unit="m3/s")
    a = m.parameter("tank.area", 2.0, unit="m2")
    k = m.parameter("tank.k", 0.1, unit="m2.5/s", uncertain=True, bounds=(0.01, 1.0))
    q_in = m.input("tank.q_in", unit="m3/s")
    m.equation(a * m.der(h), q_in - q, owner="tank")
    m.equation(q, k * sympy.sqrt(h), owner="tank")
    m.output("tank.h", h)
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import sympy as sp

from physmend.modeling.errors import ModelError
from physmend.modeling.parts import Equation, Kind, Output, Variable, der_name

if TYPE_CHECKING:
    from physmend.modeling.simplify import SimplifiedModel

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True)
class Connector:
    """An acausal connector: potentials are equal across a connection, flows sum to zero.

    Flows are positive *into* the component that owns the connector (Modelica convention).
    An unconnected connector has zero flow.
    """

    name: str
    owner: str
    potentials: tuple[sp.Symbol, ...]
    flows: tuple[sp.Symbol, ...]

    def __getattr__(self, item: str) -> sp.Symbol:
        if item.startswith("_") or item in ("name", "owner", "potentials", "flows"):
            raise AttributeError(item)
        for s in self.potentials + self.flows:
            if s.name == f"{self.name}.{item}":
                return s
        raise AttributeError(f"connector {self.name!r} has no variable {item!r}")


@dataclass
class Model:
    """A symbolic ODE/DAE model. Build it with the methods below, then call :meth:`simplify`."""

    name: str
    description: str = ""
    variables: dict[str, Variable] = field(default_factory=dict)
    equations: list[Equation] = field(default_factory=list)
    outputs: dict[str, Output] = field(default_factory=dict)
    connectors: dict[str, Connector] = field(default_factory=dict)
    connections: list[tuple[str, ...]] = field(default_factory=list)
    _ders: dict[str, sp.Symbol] = field(default_factory=dict, repr=False)

    # -- declarations -------------------------------------------------------------------------
    def affine_unit(self, unit: str, *, offset: float | None = None, base: str | None = None) -> None:
        """Declare ``unit`` a unit with an offset (an interval scale, like ``degC``): its zero is a
        convention, so a quantity in it enters a nonlinear term of a discovered formula only as a
        difference. ``offset``: how far the unit's zero lies above the absolute zero, in its own
        steps (273.15 for degC); required. ``base``: optional unit whose steps it counts (``"K"``).
        ``degC``, ``°C``, ``degF`` and ``°F`` are known without a declaration.

        Example: ``m.affine_unit("degRe", offset=218.52, base="K")`` (Réaumur).
        """
        from physmend.modeling.units import AffineUnitError, declare_affine

        try:
            declare_affine(unit, offset, base=base)
        except AffineUnitError as exc:
            raise ModelError(f"model {self.name!r}: {exc}") from None

    def _declare(self, name: str, kind: Kind, **kw: object) -> sp.Symbol:
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise ModelError(
                f"model {self.name!r}: variable names must be dotted identifiers like 'zone1.air.T', "
                f"but got {name!r}"
            )
        if name in self.variables:
            old = self.variables[name]
            raise ModelError(
                f"model {self.name!r}: variable {name!r} is declared twice "
                f"(first as {old.kind}, now as {kind})"
            )
        symbol = sp.Symbol(name, real=True)
        self.variables[name] = Variable(name=name, kind=kind, symbol=symbol, **kw)  # type: ignore[arg-type]
        return symbol

    def state(
        self, name: str, *, start: float | sp.Expr, unit: str = "", description: str = ""
    ) -> sp.Symbol:
        """Declare a differential state with its default start value (number or expression of parameters)."""
        return self._declare(
            name, "state", unit=unit, description=description, start=sp.sympify(start)
        )

    def parameter(
        self,
        name: str,
        value: float,
        *,
        unit: str = "",
        description: str = "",
        uncertain: bool = False,
        bounds: tuple[float, float] | None = None,
    ) -> sp.Symbol:
        """Declare a parameter. ``uncertain=True`` marks it for estimation within ``bounds``."""
        value = float(value)
        if bounds is not None:
            lo, hi = float(bounds[0]), float(bounds[1])
            if not lo <= value <= hi:
                raise ModelError(
                    f"model {self.name!r}: parameter {name!r} needs `low <= value <= high`, "
                    f"but got (low={lo}, value={value}, high={hi})"
                )
            bounds = (lo, hi)
        elif uncertain:
            raise ModelError(
                f"model {self.name!r}: uncertain parameter {name!r} needs bounds=(low, high)"
            )
        return self._declare(
            name,
            "parameter",
            unit=unit,
            description=description,
            value=value,
            uncertain=uncertain,
            bounds=bounds,
        )

    def input(self, name: str, *, unit: str = "", description: str = "") -> sp.Symbol:
        """Declare an exogenous input: a time series taken from the telemetry."""
        return self._declare(name, "input", unit=unit, description=description)

    def variable(self, name: str, *, unit: str = "", description: str = "") -> sp.Symbol:
        """Declare an algebraic variable, determined by the equations."""
        return self._declare(name, "algebraic", unit=unit, description=description)

    def der(self, state: sp.Symbol | str) -> sp.Symbol:
        """The time derivative of a state, for use in equations."""
        name = state if isinstance(state, str) else state.name
        var = self.variables.get(name)
        if var is None or var.kind != "state":
            kind = "undeclared" if var is None else var.kind
            raise ModelError(
                f"model {self.name!r}: der() applies to states only, but {name!r} is {kind}"
            )
        if name not in self._ders:
            self._ders[name] = sp.Symbol(der_name(name), real=True)
        return self._ders[name]

    def equation(
        self, lhs: sp.Expr | float, rhs: sp.Expr | float = 0, *, owner: str = "", label: str = ""
    ) -> Equation:
        """Add the equation ``lhs = rhs`` (``owner``: the component it belongs to)."""
        eq = Equation(sp.sympify(lhs), sp.sympify(rhs), owner=owner, label=label)
        self._check_symbols(eq.residual, f"equation {eq}")
        self.equations.append(eq)
        return eq

    def output(
        self, name: str, expr: sp.Expr | sp.Symbol, *, unit: str = "", description: str = ""
    ) -> None:
        """Declare a measured output ``name = expr`` (``name`` matches a telemetry channel)."""
        if name in self.outputs:
            raise ModelError(f"model {self.name!r}: output {name!r} is declared twice")
        expr = sp.sympify(expr)
        self._check_symbols(expr, f"output {name!r}")
        if any(s.name.startswith("der(") for s in expr.free_symbols):
            raise ModelError(
                f"model {self.name!r}: output {name!r} may not contain derivatives, but is {expr}"
            )
        self.outputs[name] = Output(name, expr, unit=unit, description=description)

    def connector(
        self,
        name: str,
        *,
        owner: str,
        potentials: dict[str, str],
        flows: dict[str, str],
    ) -> Connector:
        """Declare a connector ``name`` with potential and flow variables ``{short name: unit}``."""
        pots = tuple(self.variable(f"{name}.{k}", unit=u) for k, u in potentials.items())
        flws = tuple(self.variable(f"{name}.{k}", unit=u) for k, u in flows.items())
        con = Connector(name=name, owner=owner, potentials=pots, flows=flws)
        self.connectors[name] = con
        return con

    def connect(self, *connectors: Connector) -> None:
        """Connect two or more connectors: equal potentials, flows summing to zero.

        Connections sharing a connector are merged into one connection set, as in Modelica.
        """
        if len(connectors) < 2:
            raise ModelError(f"model {self.name!r}: connect() needs at least two connectors")
        first = connectors[0]
        shape = (len(first.potentials), len(first.flows))
        for c in connectors:
            if (len(c.potentials), len(c.flows)) != shape:
                raise ModelError(
                    f"model {self.name!r}: cannot connect {first.name!r} and {c.name!r}: "
                    "connectors have different variables"
                )
        self.connections.append(tuple(c.name for c in connectors))

    def connection_equations(self) -> list[Equation]:
        """Equations of the merged connection sets; an unconnected connector gets zero flow."""
        parent = {n: n for n in self.connectors}

        def find(n: str) -> str:
            while parent[n] != n:
                parent[n] = parent[parent[n]]
                n = parent[n]
            return n

        for group in self.connections:
            for other in group[1:]:
                parent[find(other)] = find(group[0])
        sets: dict[str, list[Connector]] = {}
        for name, con in self.connectors.items():
            sets.setdefault(find(name), []).append(con)
        eqs: list[Equation] = []
        for members in sets.values():
            first = members[0]
            if len(members) == 1:
                eqs += [Equation(f, sp.Integer(0), owner=first.owner, label=f"{first.name} (unconnected)") for f in first.flows]
                continue
            where = "connect(" + ", ".join(c.name for c in members) + ")"
            for c in members[1:]:
                eqs += [Equation(b, a, label=where) for a, b in zip(first.potentials, c.potentials)]
            for k in range(len(first.flows)):
                eqs.append(Equation(sum(c.flows[k] for c in members), sp.Integer(0), label=where))
        return eqs

    # -- queries -------------------------------------------------------------------------------
    def _check_symbols(self, expr: sp.Expr, where: str) -> None:
        known = {v.symbol for v in self.variables.values()} | set(self._ders.values())
        unknown = sorted(s.name for s in expr.free_symbols if s not in known)
        if unknown:
            raise ModelError(
                f"model {self.name!r}: {where} uses undeclared symbol(s) {unknown}; "
                "declare them with state/parameter/input/variable first"
            )

    def of_kind(self, kind: Kind) -> list[Variable]:
        return [v for v in self.variables.values() if v.kind == kind]

    def simplify(self) -> "SimplifiedModel":
        """Structural simplification: aliases removed, algebraic equations solved (exact)."""
        from physmend.modeling.simplify import simplify

        return simplify(self)

