"""The engineer's two-compartment pharmacokinetic model of a drug given by intravenous infusion:
the drug enters the central compartment (plasma) at the recorded infusion rate, is eliminated
from it with a linear clearance, and distributes to and from a peripheral compartment (tissue).
Only the plasma concentration is measured; the central volume differs between patients
(experiments)."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("pk_two_compartment", description="two-compartment pharmacokinetics, intravenous infusion, linear elimination")
    # clearances and the peripheral volume are the population values; the central volume is set per patient (data config)
    Ac = m.state("central.A", start=0.0, unit="mg", description="drug amount in the central compartment (plasma)")
    Ap = m.state("peripheral.A", start=0.0, unit="mg", description="drug amount in the peripheral compartment (tissue)")
    Vc = m.parameter("central.V", 10.0, unit="L", description="central volume (differs per patient)")
    Vp = m.parameter("peripheral.V", 25.0, unit="L", description="peripheral volume")
    CL = m.parameter("clearance.CL", 2.0, unit="L/h", description="linear elimination clearance")
    Q = m.parameter("distribution.Q", 8.0, unit="L/h", description="inter-compartmental clearance")
    rate = m.input("infusion.rate", unit="mg/h", description="intravenous infusion rate (pump log)")
    C = m.variable("central.C", unit="mg/L", description="plasma concentration")
    Cp = m.variable("peripheral.C", unit="mg/L", description="tissue concentration")
    m.equation(C, Ac / Vc, owner="central")
    m.equation(Cp, Ap / Vp, owner="peripheral")
    m.equation(m.der(Ac), rate - CL * C - Q * (C - Cp), owner="central")
    m.equation(m.der(Ap), Q * (C - Cp), owner="peripheral")
    m.output("central.C", C, unit="mg/L")
    return m
