"""The engineer's model of the Silverbox: a linear mass-spring-damper built as an electronic circuit.

The circuit integrates twice, so its output voltage ``mass.x`` (V, measured: the benchmark's V2)
is the displacement of a mass whose velocity ``mass.v`` (V/s) is not measured; the input voltage
``source.u`` (V, the benchmark's V1) is the force. Everything is written in volts and seconds:
``m·der(v) = (u − u0) − d·v − k·x``. The nominal values are a linear (best linear approximation)
fit of the first training record ``ms2``; the stiffness and the damping are declared uncertain
(estimated with the data within a factor of two), the mass and the input's DC offset are fixed.
"""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("silverbox", description="electronic mass-spring-damper (the Silverbox circuit) driven by a voltage")
    x = m.state("mass.x", start=0.0, unit="V", description="output voltage, the displacement analogue")
    v = m.state("mass.v", start=0.0, unit="V/s", description="rate of the output voltage, the velocity analogue")
    mass = m.parameter("mass.m", 5.1e-6, unit="s2", description="mass analogue (set by the integrators' time constants)")
    k = m.parameter("spring.k", 0.97, unit="1", uncertain=True, bounds=(0.5, 2.0), description="stiffness analogue")
    d = m.parameter("damper.d", 2.1e-4, unit="s", uncertain=True, bounds=(1.0e-4, 4.2e-4), description="damping analogue")
    u0 = m.parameter("source.u0", 0.0054, unit="V", description="DC offset of the input voltage")
    u = m.input("source.u", unit="V", description="input voltage, the force analogue")
    f_spring = m.variable("spring.F", unit="V")
    f_damper = m.variable("damper.F", unit="V")
    m.equation(m.der(x), v, owner="mass")
    m.equation(mass * m.der(v), (u - u0) - f_spring - f_damper, owner="mass")
    m.equation(f_spring, k * x, owner="spring")
    m.equation(f_damper, d * v, owner="damper")
    m.output("mass.x", x, unit="V")
    return m
