"""Corrections are added to the component's own equation and load back from a file."""

from __future__ import annotations

from pathlib import Path

import pytest
import sympy as sp
import torch

from physmend.modeling import Correction, ModelError, apply_corrections, compile_model, read_corrections, write_corrections
from physmend.modeling import thermal as th
from physmend.modeling.model import Model


def two_rooms() -> Model:
    m = Model("rooms")
    a = th.air_volume(m, "a", 30.0, T_start=20.0)
    b = th.air_volume(m, "b", 60.0, T_start=10.0)
    g = th.thermal_conductor(m, "wall", 5.0)
    m.connect(a.port, g.a)
    m.connect(g.b, b.port)
    m.output("a.T", a.T)
    return m


def test_correction_goes_into_the_component_equation_in_its_units(tmp_path: Path) -> None:
    base = two_rooms()
    corr = Correction(state="a.T", term="-k*(a.T - b.T)*sqrt(Abs(a.T - b.T))", constants={"k": 2.0}, unit="W")
    fixed = apply_corrections(base, [corr])
    assert len(base.equations) == len(fixed.equations) and "a.T_k" not in base.variables  # original untouched
    sm = fixed.simplify()
    assert sm.der_coefficient["a.T"] == pytest.approx(1.2 * 30.0 * 1005.0)
    assert "a.T_k" in sm.parameter_names and "+ correction" in sm.equation_text["a.T"]
    cm = compile_model(sm)
    u = torch.tensor([[20.0, 10.0]], dtype=torch.float64)
    du = cm.rhs(u, torch.zeros(1, 0, dtype=torch.float64), cm.default_parameters()[None])[0]
    C = 1.2 * 30.0 * 1005.0
    assert float(du[0]) == pytest.approx((-5.0 * 10.0 - 2.0 * 10.0 * 10.0**0.5) / C)
    path = write_corrections(tmp_path / "accepted.yaml", [corr], model="rooms", source_run_id="abc")
    items, meta = read_corrections(path)
    assert items == [corr] and meta["source_run_id"] == "abc"
    with pytest.raises(ModelError, match="never overwrites"):
        write_corrections(path, [corr])


def test_bad_corrections_are_clear_errors(tmp_path: Path) -> None:
    m = two_rooms()
    with pytest.raises(ModelError, match="'wall.Q_flow' is not a state"):
        apply_corrections(m, [Correction(state="wall.Q_flow", term="1")])
    with pytest.raises(ModelError, match="uses 'c.T', which is not a known variable"):
        apply_corrections(m, [Correction(state="a.T", term="k*c.T", constants={"k": 1.0})])
    bad = tmp_path / "bad.yaml"
    bad.write_text("corrections: []\n")
    with pytest.raises(ModelError, match="must be a physmend corrections file"):
        read_corrections(bad)
    with pytest.raises(ModelError, match="does not exist"):
        read_corrections(tmp_path / "nope.yaml")
    assert isinstance(sp.Symbol("x"), sp.Symbol)
