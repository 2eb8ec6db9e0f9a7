"""The engineer's model of a belt conveyor: a drive motor (its current logged) pulls a belt over
a head and a tail pulley. The moving mass is the drive's reduced inertia plus the belt itself
(mass per metre times the belt's length); the drive's gearbox and pulley bearings lose a force
proportional to the belt speed. Conveyors of different length are recorded (a parameter per
experiment)."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("conveyor", description="a belt conveyor driven by an electric motor")
    v = m.state("belt.v", start=0.0, unit="m/s", description="belt speed")
    L = m.parameter("belt.L", 30.0, unit="m", description="length of the conveyor (differs per installation)")
    mu = m.parameter("belt.mu", 8.0, unit="kg/m", description="belt mass per metre (both strands)")
    m0 = m.parameter("drive.m", 400.0, unit="kg", description="drive, pulleys and gearbox reduced to the belt")
    k = m.parameter("drive.k", 60.0, unit="N/A", description="motor force constant at the belt (torque constant, gearing, pulley radius)")
    b = m.parameter("drive.b", 300.0, unit="N.s/m", description="viscous loss of the gearbox and pulley bearings")
    i = m.input("motor.i", unit="A", description="motor current (drive log)")
    F = m.variable("drive.F", unit="N", description="tractive force of the drive pulley")
    m.equation(F, k * i, owner="drive")
    m.equation((m0 + mu * L) * m.der(v), F - b * v, owner="belt")
    m.output("belt.v", v, unit="m/s")
    return m
