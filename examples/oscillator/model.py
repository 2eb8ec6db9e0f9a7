"""The engineer's model of a mass on a spring with a viscous damper, driven by a shaker.

States: ``mass.x`` (m, measured) and ``mass.v`` (m/s, not measured). The damper coefficient is
declared uncertain; the mass differs between experiments (a configuration parameter).
"""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("oscillator", description="mass on a spring with a viscous damper, driven by a shaker")
    x = m.state("mass.x", start=0.0, unit="m", description="position")
    v = m.state("mass.v", start=0.0, unit="m/s", description="velocity")
    mass = m.parameter("mass.m", 1.0, unit="kg")
    k = m.parameter("spring.k", 40.0, unit="N/m")
    c = m.parameter("damper.c", 0.8, unit="N.s/m", uncertain=True, bounds=(0.4, 1.6))
    force = m.input("shaker.F", unit="N")
    f_spring = m.variable("spring.F", unit="N")
    f_damper = m.variable("damper.F", unit="N")
    m.equation(m.der(x), v, owner="mass")
    m.equation(mass * m.der(v), force - f_spring - f_damper, owner="mass")
    m.equation(f_spring, k * x, owner="spring")
    m.equation(f_damper, c * v, owner="damper")
    m.output("mass.x", x, unit="m")
    return m
