"""The engineer's model of an electric laboratory furnace: one heat capacity, a heater, and the
insulation's conductance to the room, declared uncertain (it is estimated with the data)."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("furnace", description="electric furnace heated by a recorded power program")
    T = m.state("chamber.T", start=295.0, unit="K", description="chamber temperature")
    C = m.parameter("chamber.C", 5.0e4, unit="J/K", description="heat capacity of the chamber and load")
    UA = m.parameter("insulation.UA", 20.0, unit="W/K", uncertain=True, bounds=(10.0, 40.0),
                     description="conductance of the insulation")
    P = m.input("heater.P", unit="W")
    T_room = m.input("room.T", unit="K")
    Q = m.variable("insulation.Q_flow", unit="W", description="heat lost through the insulation")
    m.equation(Q, UA * (T - T_room), owner="insulation")
    m.equation(C * m.der(T), P - Q, owner="chamber")
    m.output("chamber.T", T, unit="K")
    return m
