"""Acausal thermal components built on heat ports, assembled like a Modelica user would.

Each function adds one component's variables and equations to a :class:`Model` and returns the
component, whose heat ports are connected with ``model.connect(a.port, b.port)``. Heat ports carry
a temperature ``T`` and a heat flow ``Q_flow`` (W), positive into the component. Parameters may be
numbers or sympy expressions of model parameters (e.g. a capacity computed from a zone length).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import sympy as sp

from physmend.modeling.model import Connector, Model

Number = float | sp.Expr


@dataclass(frozen=True)
class Component:
    """A component instance: its name, heat ports, states and other named variables."""

    name: str
    ports: dict[str, Connector]
    vars: dict[str, sp.Symbol] = field(default_factory=dict)
    parts: dict[str, "Component"] = field(default_factory=dict)

    def __getattr__(self, item: str) -> Connector | sp.Symbol | "Component":
        if item.startswith("_") or item in ("name", "ports", "vars", "parts"):
            raise AttributeError(item)
        for table in (self.ports, self.vars, self.parts):
            if item in table:
                return table[item]
        raise AttributeError(f"component {self.name!r} has no port, variable or part {item!r}")


def heat_port(m: Model, name: str, owner: str, T_unit: str = "K") -> Connector:
    return m.connector(name, owner=owner, potentials={"T": T_unit}, flows={"Q_flow": "W"})


def heat_capacitor(
    m: Model, name: str, C: Number, *, T_start: Number, T_unit: str = "K", description: str = ""
) -> Component:
    """Lumped thermal mass: ``C dT/dt = port.Q_flow`` with ``C`` in J/K."""
    T = m.state(f"{name}.T", start=T_start, unit=T_unit, description=description or f"temperature of {name}")
    port = heat_port(m, f"{name}.port", name, T_unit)
    m.equation(C * m.der(T), port.Q_flow, owner=name, label=f"{name}: energy balance")
    m.equation(port.T, T, owner=name, label=f"{name}: port temperature")
    return Component(name, {"port": port}, {"T": T})


def air_volume(
    m: Model,
    name: str,
    volume: Number,
    *,
    T_start: Number,
    density: Number = 1.2,
    cp: Number = 1005.0,
    T_unit: str = "K",
) -> Component:
    """Well-mixed air volume (m³), density kg/m³, cp J/(kg·K): a heat capacitor of ρ·V·cp."""
    return heat_capacitor(
        m, name, density * volume * cp, T_start=T_start, T_unit=T_unit, description=f"air temperature of {name}"
    )


def thermal_conductor(m: Model, name: str, G: Number, *, T_unit: str = "K") -> Component:
    """Linear conductance ``G`` (W/K) between ports a and b: ``Q = G (a.T - b.T)`` from a to b."""
    a = heat_port(m, f"{name}.a", name, T_unit)
    b = heat_port(m, f"{name}.b", name, T_unit)
    Q = m.variable(f"{name}.Q_flow", unit="W", description=f"heat flow through {name}, a to b")
    m.equation(Q, G * (a.T - b.T), owner=name, label=f"{name}: conduction")
    m.equation(a.Q_flow, Q, owner=name, label=f"{name}: flow in at a")
    m.equation(b.Q_flow, -Q, owner=name, label=f"{name}: flow out at b")
    return Component(name, {"a": a, "b": b}, {"Q_flow": Q})


def convection(m: Model, name: str, h: Number, area: Number, *, T_unit: str = "K") -> Component:
    """Convective film: coefficient ``h`` (W/(m²·K)) over ``area`` (m²); a conductor of h·A."""
    return thermal_conductor(m, name, h * area, T_unit=T_unit)


def prescribed_temperature(m: Model, name: str, T: Number, *, T_unit: str = "K") -> Component:
    """Boundary at a given temperature (an input, a parameter or an expression)."""
    port = heat_port(m, f"{name}.port", name, T_unit)
    m.equation(port.T, T, owner=name, label=f"{name}: prescribed temperature")
    return Component(name, {"port": port})


def prescribed_heat_flow(m: Model, name: str, Q: Number, *, T_unit: str = "K") -> Component:
    """Heat flow ``Q`` (W) delivered *into* the connected component (negative Q extracts heat)."""
    port = heat_port(m, f"{name}.port", name, T_unit)
    m.equation(port.Q_flow, -Q, owner=name, label=f"{name}: prescribed heat flow")
    return Component(name, {"port": port})


def layered_wall(
    m: Model,
    name: str,
    *,
    area: Number,
    thickness: Number,
    conductivity: Number,
    density: Number,
    cp: Number,
    n_layers: int,
    T_start: Number,
    T_unit: str = "K",
) -> Component:
    """Plane wall discretised along its thickness into ``n_layers`` lumped layers.

    Port ``a`` is one face, port ``b`` the other. Layer ``i`` has capacity ρ·cp·A·Δx; adjacent
    layer centres are joined by k·A/Δx, each face to its layer centre by 2·k·A/Δx.
    """
    if n_layers < 1:
        from physmend.modeling.errors import ModelError

        raise ModelError(f"wall {name!r}: `n_layers >= 1` must hold, but got n_layers={n_layers}")
    dx = thickness / n_layers
    layers = [
        heat_capacitor(m, f"{name}.layer{i + 1}", density * cp * area * dx, T_start=T_start, T_unit=T_unit)
        for i in range(n_layers)
    ]
    face_a = thermal_conductor(m, f"{name}.face_a", 2 * conductivity * area / dx, T_unit=T_unit)
    face_b = thermal_conductor(m, f"{name}.face_b", 2 * conductivity * area / dx, T_unit=T_unit)
    m.connect(face_a.b, layers[0].port)
    for i in range(n_layers - 1):
        g = thermal_conductor(m, f"{name}.cond{i + 1}", conductivity * area / dx, T_unit=T_unit)
        m.connect(layers[i].port, g.a)
        m.connect(g.b, layers[i + 1].port)
    m.connect(layers[-1].port, face_b.a)
    parts = {f"layer{i + 1}": c for i, c in enumerate(layers)}
    return Component(name, {"a": face_a.a, "b": face_b.b}, {}, parts)
