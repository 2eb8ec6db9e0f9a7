"""The engineer's equivalent circuit of a Li-ion cell: charge counting, one polarisation RC
branch, a series resistance and an open-circuit-voltage curve. Only the terminal voltage is
measured; the cell's capacity differs between cells (experiments)."""

from __future__ import annotations

import sympy as sp

from physmend.modeling import Model


def build() -> Model:
    m = Model("battery", description="Li-ion cell, first-order equivalent circuit")
    soc = m.state("cell.soc", start=0.9, unit="1", description="state of charge")
    v1 = m.state("rc.v", start=0.0, unit="V", description="polarisation voltage")
    Q = m.parameter("cell.Q", 9000.0, unit="A.s", description="capacity")
    R0 = m.parameter("cell.R0", 0.03, unit="Ohm")
    R1 = m.parameter("rc.R", 0.02, unit="Ohm")
    C1 = m.parameter("rc.C", 10000.0, unit="F")
    i = m.input("load.i", unit="A", description="discharge current (positive out of the cell)")
    ocv = m.variable("cell.ocv", unit="V", description="open-circuit voltage")
    V = m.variable("cell.V", unit="V", description="terminal voltage")
    m.equation(Q * m.der(soc), -i, owner="cell")
    m.equation(C1 * m.der(v1), i - v1 / R1, owner="rc")
    m.equation(ocv, 3.4 + 0.6 * soc + 0.1 * sp.tanh(20 * (soc - 0.1)), owner="cell")
    m.equation(V, ocv - R0 * i - v1, owner="cell")
    m.output("cell.V", V, unit="V")
    return m
