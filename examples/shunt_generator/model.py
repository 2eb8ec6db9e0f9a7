"""The engineer's model of a self-excited DC shunt generator building up its voltage: the field
winding (inductance and resistance, the field rheostat set per experiment) fed by the armature's
own emf, which grows with the field current through the magnetisation line of the iron — taken as
a straight line (residual flux plus a constant slope) — and with the shaft speed (tachometer)."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("shunt_generator", description="self-excited DC shunt generator at no load, voltage build-up")
    i = m.state("field.i", start=0.0, unit="A", description="field current")
    L = m.parameter("field.L", 20.0, unit="H", description="inductance of the field winding")
    R = m.parameter("field.R", 56.0, unit="Ohm", description="field winding plus rheostat (set per experiment)")
    k_r = m.parameter("machine.k_r", 0.01, unit="V.s/rad", description="emf constant of the residual flux")
    G = m.parameter("machine.G", 0.5, unit="V.s/(rad.A)", description="slope of the magnetisation line (emf per speed and field current)")
    w = m.input("shaft.w", unit="rad/s", description="shaft speed of the prime mover")
    E = m.variable("armature.E", unit="V", description="emf induced in the armature")
    m.equation(E, w * (k_r + G * i), owner="armature")
    m.equation(L * m.der(i), E - R * i, owner="field")
    m.output("field.i", i, unit="A")
    return m
