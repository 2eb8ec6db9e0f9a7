"""The unit a correction is reported in: the unit of its equation's terms, not of its symbols."""

from __future__ import annotations

from pathlib import Path

import pytest

from physmend.config import compose
from physmend.problem import load_problem
from physmend.stages.symbolic import equation_unit

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
