"""The unit a correction is reported in: the unit of its equation's terms, not of its symbols."""

from __future__ import annotations

from pathlib import Path

import pytest

from physmend.config import compose
from physmend.problem import load_problem
from physmend.symbolic.targets import equation_unit

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.parametrize("example, state, unit", [
    ("furnace", "chamber.T", "W"),            # C·der(T) = P − UA·(T − T_room): a watts term of temperatures
    ("oscillator", "mass.v", "N"),            # m·der(v) = F − k·x − c·v: a force
    ("oscillator", "mass.x", "m/s"),          # der(x) = v: a rate in the state's unit per second
    ("predator_prey", "prey.x", "kanimals/tu"),  # der(x) = …, in the model's own time unit
])
def test_a_correction_is_labelled_in_its_equations_units(example: str, state: str, unit: str) -> None:
    cfg = compose([f"model={example}", f"data={example}"], user_config_dir=EXAMPLES / example / "conf")
    problem = load_problem(cfg)
    assert equation_unit(problem.model, state, problem.time_unit) == unit


def test_the_label_is_the_unit_whose_dimension_the_equation_has() -> None:
    """A heat balance whose alphabetically first variable is a temperature is still labelled in W."""
    from physmend.modeling import Model

    m = Model("room")
    T = m.state("T", start=290.0, unit="K")
    C = m.parameter("C", 1e5, unit="J/K")
    G = m.parameter("G", 50.0, unit="W/K")
    Ta = m.input("Ta", unit="degC")
    q = m.input("q", unit="kW")
    m.equation(C * m.der(T), G * (Ta - T) + 1000 * q)
    m.output("T", T, unit="K")
    assert equation_unit(m.simplify(), "T") == "kW"
