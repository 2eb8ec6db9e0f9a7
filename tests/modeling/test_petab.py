"""The PEtab writer's pieces: SBML formulas that a simulator outside physmend (libRoadRunner)
evaluates to the model's values, recorded inputs interpolated exactly as physmend does, and clear
errors for what SBML cannot hold."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from physmend.modeling import Model
from physmend.modeling.errors import ModelError
from physmend.modeling.petab import identifiers, interpolation, l3

libsbml = pytest.importorskip("libsbml", reason="python-libsbml is part of the test extra (pip install -e '.[test]')")
roadrunner = pytest.importorskip("roadrunner", reason="libroadrunner is part of the test extra")


def _document(rules: dict[str, str], constants: dict[str, float]) -> str:
    doc = libsbml.SBMLDocument(3, 2)
    m = doc.createModel()
    m.setId("m")
    for name, value in constants.items():
        p = m.createParameter()
        p.setId(name), p.setValue(value), p.setConstant(True)
    for name, formula in rules.items():
        p = m.createParameter()
        p.setId(name), p.setValue(0.0), p.setConstant(False)
        rule = m.createAssignmentRule()
        rule.setVariable(name)
        ast = libsbml.parseL3Formula(formula)
        assert ast is not None, (formula, libsbml.getLastParseL3Error())
        rule.setMath(ast)
    return libsbml.writeSBMLToString(doc)


def test_formulas_evaluate_to_the_models_values_outside_physmend() -> None:
    a, b = sp.symbols("tank.a tank.b")
    exprs = {
        "f1": sp.Float(1.5) * (a - b) * sp.sqrt(sp.Abs(a - b)),
        "f2": sp.Min(a, b) + sp.Max(a, sp.Integer(0)) - sp.sign(b - a) * sp.Float(0.6),
        "f3": sp.exp(-a / 3) + sp.log(b) + sp.tanh(a - b) + a ** sp.Rational(3, 2) + b ** -1,
        "f4": sp.Piecewise((a, a > b), (b, True)) + sp.Heaviside(a - 2),
    }
    values = {"tank.a": 2.5, "tank.b": 0.7}
    ids = {"tank.a": "tank_a", "tank.b": "tank_b"}
    rr = roadrunner.RoadRunner(_document({k: l3(e, ids) for k, e in exprs.items()},
                                         {ids[k]: v for k, v in values.items()}))
    for name, e in exprs.items():
        want = float(e.subs({a: values["tank.a"], b: values["tank.b"]}))
        assert rr[name] == pytest.approx(want, rel=1e-12), name


def test_recorded_inputs_are_interpolated_as_physmend_does() -> None:
    t = np.array([-5.0, 0.0, 10.0, 20.0, 30.0, 40.0, 55.0, 70.0])
    v = np.array([1.0, 1.0, 3.0, 5.0, 7.0, 2.0, 2.0, 4.0])  # 10..30 collinear: one segment in the SBML
    rr = roadrunner.RoadRunner(_document({"u": interpolation(t, v)}, {}))
    grid = np.array([0.0, 3.0, 10.0, 17.5, 29.0, 33.0, 40.0, 60.0, 70.0, 80.0])
    sim = rr.simulate(times=grid, selections=["time", "u"])
    assert sim[:, 1] == pytest.approx(np.interp(grid, t, v), abs=1e-12)  # end values held beyond the samples
    assert interpolation(t, v).count("piecewise") < interpolation(t, v + np.arange(t.size) ** 2).count("piecewise")


def test_what_sbml_cannot_hold_is_one_clear_line() -> None:
    x = sp.Symbol("x")
    with pytest.raises(ModelError, match="SBML has no function for erf"):
        l3(sp.erf(x), {"x": "x"})
    with pytest.raises(ModelError, match="'y' is neither a state, an input nor a parameter"):
        l3(sp.Symbol("y") + x, {"x": "x"})
    m = Model("clash")
    s = m.state("a.b", start=0.0)
    k = m.parameter("a_b", 1.0)
    m.equation(m.der(s), -k)
    with pytest.raises(ModelError, match="'a_b' and 'a.b' both become the SBML identifier 'a_b'"):
        identifiers(m.simplify())
