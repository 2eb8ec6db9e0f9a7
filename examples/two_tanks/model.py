"""The engineer's model of two tanks in cascade: a pump fills the upper tank, which drains through
an orifice into the lower tank, which drains through a valve. Only the lower tank's level is
measured; the valve setting differs between experiments."""

from __future__ import annotations

import sympy as sp

from physmend.modeling import Model


def build() -> Model:
    m = Model("two_tanks", description="two tanks in cascade, Torricelli outlets")
    # areas and the orifice are known from the drawings; the valve is set per experiment (data config)
    h1 = m.state("tank1.h", start=0.3, unit="m", description="upper tank level (not measured)")
    h2 = m.state("tank2.h", start=0.3, unit="m", description="lower tank level")
    A1 = m.parameter("tank1.A", 0.5, unit="m2")
    A2 = m.parameter("tank2.A", 0.25, unit="m2")
    k1 = m.parameter("orifice.k", 0.004, unit="m2.5/s")
    k2 = m.parameter("valve.k", 0.004, unit="m2.5/s", description="valve setting")
    q_in = m.input("pump.q", unit="m3/s")
    q12 = m.variable("orifice.q", unit="m3/s", description="flow from tank 1 into tank 2")
    q_out = m.variable("valve.q", unit="m3/s", description="flow out of tank 2")
    m.equation(q12, k1 * sp.sqrt(h1), owner="orifice")
    m.equation(q_out, k2 * sp.sqrt(h2), owner="valve")
    m.equation(A1 * m.der(h1), q_in - q12, owner="tank1")
    m.equation(A2 * m.der(h2), q12 - q_out, owner="tank2")
    m.output("tank2.h", h2, unit="m")
    return m
