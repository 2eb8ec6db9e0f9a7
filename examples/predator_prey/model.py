"""The engineer's model of a prey and a predator population in dimensionless time.

Prey grow logistically up to the carrying capacity ``prey.K`` of their habitat (it differs between
habitats, i.e. experiments) and are stocked from a hatchery at a recorded rate ``stocking.u``;
predators grow by feeding on prey, die at a constant rate and compete among themselves. Both
populations are counted (thousands of animals); time is in the model's own unit ``tu``.
"""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("predator_prey", description="prey and predators, logistic prey growth, stocked prey")
    x = m.state("prey.x", start=2.0, unit="kanimals", description="prey population")
    y = m.state("pred.y", start=1.0, unit="kanimals", description="predator population")
    r = m.parameter("prey.r", 1.0, unit="1/tu", description="prey growth rate")
    K = m.parameter("prey.K", 6.0, unit="kanimals", description="carrying capacity of the habitat")
    b = m.parameter("pred.b", 0.2, unit="1/(kanimals.tu)", description="predator growth per prey eaten")
    d = m.parameter("pred.d", 0.6, unit="1/tu", description="predator death rate")
    e = m.parameter("pred.e", 0.15, unit="1/(kanimals.tu)", description="competition among predators")
    u = m.input("stocking.u", unit="kanimals/tu", description="prey released from the hatchery")
    m.equation(m.der(x), r * x * (1 - x / K) + u, owner="prey")
    m.equation(m.der(y), b * x * y - d * y - e * y**2, owner="pred")
    m.output("prey.x", x, unit="kanimals")
    m.output("pred.y", y, unit="kanimals")
    return m
