"""Dimensions of declared units (Modelica notation) and of formulas built from them."""

from __future__ import annotations

import pytest
import sympy as sp

from physmend.modeling.units import ANY, UnitMismatch, dimension, formula_dimension, mismatch, same


@pytest.mark.parametrize("a, b", [
    ("W", "J/s"), ("W", "kg.m2/s3"), ("W", "kg*m^2/s^3"), ("W/K", "J/(s.K)"), ("N", "kg.m/s2"),
    ("Ohm", "V/A"), ("F", "A.s/V"), ("mm", "m"), ("kW", "W"), ("degC", "K"), ("m3/s", "L/min"),
    ("1/(kanimals.tu)", "kanimals-1.tu-1"), ("m2.5/s", "m2.m0.5/s"), ("%", "1"),
])
def test_units_written_differently_have_one_dimension(a: str, b: str) -> None:
    da, db = dimension(a), dimension(b)
    assert da is not None and db is not None and same(da, db), (a, da, b, db)


@pytest.mark.parametrize("a, b", [("W", "K"), ("m3/s", "m/s"), ("kanimals/tu", "kanimals"), ("N", "N/m")])
def test_different_units_have_different_dimensions(a: str, b: str) -> None:
    da, db = dimension(a), dimension(b)
    assert da is not None and db is not None and not same(da, db)


@pytest.mark.parametrize("unit", ["", "  ", "m/(s", "2/s", "m^^2"])
def test_an_unreadable_unit_is_unknown_not_an_error(unit: str) -> None:
    assert dimension(unit) is None


T, T2, Q, x = sp.symbols("T T2 Q x")
UNITS = {"T": "K", "T2": "degC", "Q": "W", "x": "1"}


@pytest.mark.parametrize("expr, why", [
    (T + Q, "inconsistent units"),                    # a temperature plus a heat flow
    (sp.exp(T), "not a pure number"),                 # a function of a temperature
    (T - T2, "cannot be the equation's W"),           # kelvin where watts are needed, no constant to carry it
    (sp.Max(Q, T), "inconsistent units"),
    (Q ** T, "not a pure number"),
])
def test_a_formula_whose_units_cannot_match_is_named(expr: sp.Expr, why: str) -> None:
    reason = mismatch(expr, UNITS, "W")
    assert reason is not None and why in reason, reason


@pytest.mark.parametrize("expr", [
    2.5 * T + Q,                                      # a fitted constant may be in W/K
    sp.Float(1.2) * (T - T2) * sp.sqrt(sp.Abs(T - T2)),
    sp.Float(3e-9) * (T ** 4 - T2 ** 4),
    Q * sp.sign(T - T2),
    Q * sp.exp(sp.Float(0.01) * T) + sp.Float(4.0),
    sp.Float(7.0) * x,                                # a pure number times a constant
    sp.Min(Q, sp.Float(150.0)),
    sp.Float(2.0) * sp.Max(T - T2, 0),                # a threshold at zero is in any unit
])
def test_a_formula_a_constant_can_make_consistent_passes(expr: sp.Expr) -> None:
    assert mismatch(expr, UNITS, "W") is None


def test_unknown_units_are_never_a_reason() -> None:
    y = sp.Symbol("y")  # no unit declared
    assert formula_dimension(y + T, {"T": "K"}) == dimension("K")
    assert formula_dimension(y * T, {"T": "K"}) is ANY
    assert mismatch(T, {"T": "K"}, "") is None
    with pytest.raises(UnitMismatch):
        formula_dimension(T + Q, UNITS)
