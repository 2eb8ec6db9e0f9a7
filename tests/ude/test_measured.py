"""Outputs that measure a state through a factor of the parameters (a concentration A/V of an
amount) count as measurements of the state; other outputs measure no single state."""

from __future__ import annotations

import pytest
import torch

from physmend.modeling import Model
from physmend.ude.measured import factors, measured_outputs


def _model() -> Model:
    m = Model("pk")
    a = m.state("central.A", start=0.0, unit="mg")
    b = m.state("tissue.A", start=0.0, unit="mg")
    v = m.parameter("central.V", 10.0, unit="L")
    w = m.parameter("tissue.V", 20.0, unit="L")
    u = m.input("pump.rate", unit="mg/h")
    c = m.variable("central.C", unit="mg/L")
    m.equation(c, a / v)
    m.equation(m.der(a), u - 2 * c)
    m.equation(m.der(b), 0.1 * a - 0.1 * b)
    m.output("central.C", c, unit="mg/L")                  # A / V: measures central.A
    m.output("tissue.A", b, unit="mg")                     # the state itself
    m.output("offset", a / v + 1, unit="mg/L")             # not proportional: an offset
    m.output("total", (a + b) / w, unit="mg/L")            # two states
    m.output("driven", a * u / v, unit="mg2/(L.h)")        # an input in the factor
    return m


def test_a_state_times_a_factor_of_the_parameters_is_a_measurement_of_it() -> None:
    sm = _model().simplify()
    found = measured_outputs(sm)
    assert [(sm.output_names[j], sm.state_names[i]) for j, i, _ in found] == [("central.C", "central.A"), ("tissue.A", "tissue.A")]
    p = torch.tensor([[8.0, 20.0], [12.0, 20.0]])  # central.V differs between experiments
    order = sm.parameter_names
    p = p[:, [["central.V", "tissue.V"].index(n) for n in order]]
    g = factors(sm)(p)
    assert g.shape == (2, 2)
    assert g[:, 0].tolist() == pytest.approx([1 / 8, 1 / 12]) and g[:, 1].tolist() == [1.0, 1.0]


def test_the_recorded_quantities_are_the_scaled_outputs_that_are_model_variables() -> None:
    from physmend.ude.measured import recorded_quantities

    sm = _model().simplify()
    assert recorded_quantities(sm, ["central.C", "offset"]) == ["central.C"]  # tissue.A is a state: not one
    assert recorded_quantities(sm, ["central.C"], states=["tissue.A"]) == []
