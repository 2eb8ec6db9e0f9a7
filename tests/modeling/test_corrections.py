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


def test_recalibrated_parameters_travel_with_the_terms_and_only_declared_uncertain_ones(tmp_path: Path) -> None:
    base = two_rooms()
    corr = Correction(state="a.T", term="k*(b.T - a.T)", constants={"k": 1.0}, unit="W")
    name, lo, hi = "wall.extra", 0.5, 2.0  # declared uncertain, as a user would
    base.parameter(name, 1.0, uncertain=True, bounds=(lo, hi))
    base.parameter("wall.fixed", 3.0)
    value = 1.25
    path = write_corrections(tmp_path / "c.yaml", [corr], parameters={name: value}, model="rooms")
    items, meta = read_corrections(path)
    assert meta["parameters"] == {name: value}
    fixed = apply_corrections(base, items, parameters=meta["parameters"])
    assert fixed.variables[name].value == value and base.variables[name].value == 1.0  # the original untouched
    # a parameter that is not declared uncertain, one out of its bounds, and a non-number are refused
    fixed_name = "wall.fixed"
    with pytest.raises(ModelError, match=f"parameters.'{fixed_name}'.*declares uncertain"):
        apply_corrections(base, items, parameters={fixed_name: 1.0})
    with pytest.raises(ModelError, match=f"parameters.{name} must be a finite number within its declared bounds"):
        apply_corrections(base, items, parameters={name: hi * 10 + 1})
    bad = tmp_path / "bad.yaml"
    bad.write_text(path.read_text().replace(f"{name}: {value}", f"{name}: abc"))
    with pytest.raises(ModelError, match=f"parameters.'{name}' must be a number, but is 'abc'"):
        read_corrections(bad)
    # no parameters: the file reads as before (an empty mapping)
    plain = write_corrections(tmp_path / "plain.yaml", [corr])
    assert read_corrections(plain)[1]["parameters"] == {} and "parameters" not in plain.read_text()


def test_a_corrected_model_built_after_its_base_is_the_one_built_alone() -> None:
    """Rows, blocks and functions a corrected model shares with the model as written are split,
    solved and lambdified once per process (``_row_split``, ``_SOLVED``, ``_LAMBDIFIED``): built
    after its base it reuses them, and its equations,
    affine split and derivatives are exactly those it has when built in a process that built nothing."""
    from physmend.modeling import compile as compiling
    from physmend.modeling import lambdify as lambdifying
    from physmend.modeling import simplify as simplifying

    corr = Correction(state="a.T", term="-k*(a.T - b.T)*sqrt(Abs(a.T - b.T))", constants={"k": 2.0}, unit="W")

    def built() -> tuple:
        sm = apply_corrections(two_rooms(), [corr]).simplify()
        cm = compile_model(sm)
        u = torch.tensor([[20.0, 10.0], [5.0, 7.5]], dtype=torch.float64)
        du = cm.rhs(u, torch.zeros(2, 0, dtype=torch.float64), cm.default_parameters().expand(2, -1))
        split = cm._affine
        return sm.rhs, split.constant, split.varying, split.nonlinear, split.rest_args, du

    compiling._row_split.cache_clear()
    simplifying._SOLVED.clear()
    lambdifying._LAMBDIFIED.clear()
    alone = built()
    compiling._row_split.cache_clear()
    simplifying._SOLVED.clear()
    lambdifying._LAMBDIFIED.clear()
    compile_model(two_rooms().simplify())  # the model as written first, as every stage of discover builds it
    hits = compiling._row_split.cache_info().hits
    after = built()
    assert compiling._row_split.cache_info().hits > hits  # the row b.T shares was not split again
    assert after[:5] == alone[:5]
    assert torch.equal(after[5], alone[5])
