"""``ude.inputs.parameters: auto``: a parameter is a network input when it takes 3+ values in training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from physmend.data import load_experiments
from physmend.modeling import Model, compile_model
from physmend.problem import Problem
from physmend.ude.spec import informative_parameters


def _problem(tmp_path: Path, areas: list[float], roles: list[str]) -> Problem:
    m = Model("tank")
    h = m.state("tank.h", start=1.0, unit="m")
    area = m.parameter("tank.area", 2.0, unit="m2")
    m.parameter("tank.k", 0.1, unit="m2/s")
    q = m.input("pump.q", unit="m3/s")
    m.equation(area * m.der(h), q, owner="tank")
    m.output("tank.h", h)
    model = m.simplify()
    rows = []
    for i, (a, role) in enumerate(zip(areas, roles)):
        t = np.arange(20.0)
        pd.DataFrame({"time": t, "tank.h": 1 + 0.01 * t, "pump.q": np.ones(20)}).to_csv(tmp_path / f"{i}.csv", index=False)
        rows.append({"id": str(i), "file": f"{i}.csv", "role": role, "parameters": {"tank.area": a}})
    data = {"name": "tank", "root": str(tmp_path), "experiments": rows}
    return Problem(model=model, compiled=compile_model(model), experiments=load_experiments(data, model),
                   dtype=torch.float64)


def test_two_values_label_experiments_three_describe_them(tmp_path: Path) -> None:
    two = _problem(tmp_path, [1.0, 2.0, 1.0, 5.0], ["train", "train", "train", "test"])
    assert informative_parameters(two) == []  # 5.0 is a test value: it counts for nothing
    three = _problem(tmp_path, [1.0, 2.0, 3.0, 5.0], ["train", "train", "train", "test"])
    assert informative_parameters(three) == ["tank.area"]  # tank.k never varies


def test_state_and_input_selection_takes_switches_or_patterns() -> None:
    import pytest

    from physmend.ude.hybrid import UDEConfigError
    from physmend.ude.spec import _selected

    names = ["zone1.air.T", "zone1.wall.T", "zone2.air.T"]
    assert _selected(True, names, "ude.inputs.states") == names
    assert _selected(False, names, "ude.inputs.states") == []
    assert _selected(["zone2.air.T", "zone1.air*"], names, "ude.inputs.states") == ["zone1.air.T", "zone2.air.T"]
    with pytest.raises(UDEConfigError, match=r"ude.inputs.states: pattern 'cargo\.T' matches no name"):
        _selected(["cargo.T"], names, "ude.inputs.states")
    with pytest.raises(UDEConfigError, match="ude.inputs.inputs must be true, false or a list"):
        _selected("some", names, "ude.inputs.inputs")


def test_a_word_for_the_state_or_input_selection_is_refused_when_composed() -> None:
    import pytest

    from physmend.config import ConfigError, compose

    with pytest.raises(ConfigError, match="ude.inputs.states must be true, false or a list of names/patterns, but got 'some'"):
        compose(["ude.inputs.states=some"])
    cfg = compose(["ude.inputs.states=[zone1.air.T]", "ude.inputs.inputs=false"])
    assert list(cfg.ude.inputs.states) == ["zone1.air.T"] and cfg.ude.inputs.inputs is False
