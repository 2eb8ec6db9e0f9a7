"""The engineer's model of a continuous stirred-tank reactor in the lab: a feed of reactant A and
an additive B (fixed feed concentrations, the pump's flow recorded) runs through a well-mixed
vessel of fixed volume. A decomposes by a known first-order reaction; B is taken to be inert.
Both concentrations are analysed in samples drawn by hand; time is in minutes."""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("cstr", description="a stirred-tank reactor, first-order decomposition of A, B inert")
    A = m.state("reactor.A", start=0.2, unit="mol/L", description="concentration of the reactant A")
    B = m.state("reactor.B", start=2.5, unit="mol/L", description="concentration of the additive B")
    V = m.parameter("reactor.V", 10.0, unit="L", description="liquid volume (overflow weir)")
    A_in = m.parameter("feed.A", 2.0, unit="mol/L", description="A in the feed")
    B_in = m.parameter("feed.B", 3.0, unit="mol/L", description="B in the feed")
    k1 = m.parameter("decomp.k", 0.03, unit="1/min", description="first-order decomposition of A")
    q = m.input("feed.q", unit="L/min", description="feed flow (rotameter, read at each sample)")
    m.equation(m.der(A), q / V * (A_in - A) - k1 * A, owner="reactor")
    m.equation(m.der(B), q / V * (B_in - B), owner="reactor")
    m.output("reactor.A", A, unit="mol/L")
    m.output("reactor.B", B, unit="mol/L")
    return m
