"""The engineer's model of a prey and predator population in dimensionless time.

Prey grow logistically up to the carrying capacity ``prey.K`` (differs between habitats, i.e.
experiments); predators grow by feeding on prey, die at a constant rate and compete among themselves. Both populations are
counted (thousands of animals).
"""

from __future__ import annotations

from physmend.modeling import Model


def build() -> Model:
    m = Model("predator_prey", description="prey and predators, logistic prey growth")
    x = m.state("prey.x", start=2.0, unit="kanimals", description="prey population")
    y = m.state("pred.y", start=1.0, unit="kanimals", description="predator population")
    r = m.parameter("prey.r", 1.0, unit="1/tu", description="prey growth rate")
    K = m.parameter("prey.K", 5.0, unit="kanimals", description="carrying capacity of the habitat")
    b = m.parameter("pred.b", 0.3, unit="1/(kanimals.tu)", description="predator growth per prey eaten")
    d = m.parameter("pred.d", 0.6, unit="1/tu", description="predator death rate")
    e = m.parameter("pred.e", 0.2, unit="1/(kanimals.tu)", description="competition among predators")
    m.equation(m.der(x), r * x * (1 - x / K), owner="prey")
    m.equation(m.der(y), b * x * y - d * y - e * y**2, owner="pred")
    m.output("prey.x", x, unit="kanimals")
    m.output("pred.y", y, unit="kanimals")
    return m
