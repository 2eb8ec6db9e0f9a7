"""The engineer's model of a small greenhouse: one air-and-plants heat capacity, the envelope's
conductance to the outdoors, and a recorded heater. Glazing area differs between houses."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("greenhouse", description="a greenhouse zone over days")
    T = m.state("zone.T", start=15.0, unit="degC", description="air (and plant) temperature")
    C = m.parameter("zone.C", 4.0e6, unit="J/K", description="heat capacity of air, plants and benches")
    UA = m.parameter("envelope.UA", 600.0, unit="W/K", description="conductance of the envelope")
    m.parameter("glazing.area", 6.0, unit="m2", description="glazed area of the house")
    T_out = m.input("outdoor.T", unit="degC")
    m.input("sun.I", unit="W/m2", description="solar irradiance on the horizontal")
    P = m.input("heater.P", unit="W")
    Q_env = m.variable("envelope.Q_flow", unit="W", description="heat lost through the envelope")
    m.equation(Q_env, UA * (T - T_out), owner="envelope")
    m.equation(C * m.der(T), P - Q_env, owner="zone")
    m.output("zone.T", T, unit="degC")
    return m
