"""The engineer's model of an outdoor telecom cabinet: the electronics (one heat capacity, their
recorded power), the air inside the cabinet, and the walls' conductance to the outdoors, declared
uncertain (it is estimated with the data). Temperatures in degrees Celsius, as the logger records."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("telecom_cabinet", description="outdoor telecom cabinet heated by its electronics")
    T_eq = m.state("equipment.T", start=20.0, unit="degC", description="chassis temperature of the electronics")
    T_air = m.state("cabinet.air.T", start=15.0, unit="degC", description="air temperature inside the cabinet")
    C_eq = m.parameter("equipment.C", 3.0e4, unit="J/K", description="heat capacity of the electronics and their chassis")
    G_eq = m.parameter("equipment.G", 25.0, unit="W/K", description="conductance from the chassis to the cabinet air (fans, fins)")
    C_air = m.parameter("cabinet.air.C", 1.5e4, unit="J/K", description="heat capacity of the air, shelves and inner walls")
    UA = m.parameter("walls.UA", 8.0, unit="W/K", uncertain=True, bounds=(4.0, 16.0),
                     description="conductance of the insulated walls, door and gaskets")
    P = m.input("equipment.P", unit="W", description="electrical power drawn by the electronics (all of it becomes heat)")
    T_out = m.input("outdoor.T", unit="degC")
    Q_eq = m.variable("equipment.Q_flow", unit="W", description="heat from the chassis into the cabinet air")
    Q_walls = m.variable("walls.Q_flow", unit="W", description="heat lost through the walls")
    m.equation(Q_eq, G_eq * (T_eq - T_air), owner="equipment")
    m.equation(Q_walls, UA * (T_air - T_out), owner="walls")
    m.equation(C_eq * m.der(T_eq), P - Q_eq, owner="equipment")
    m.equation(C_air * m.der(T_air), Q_eq - Q_walls, owner="cabinet")
    m.output("equipment.T", T_eq, unit="degC")
    m.output("cabinet.air.T", T_air, unit="degC")
    return m
