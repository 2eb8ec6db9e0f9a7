"""The operators ``sin``, ``cos`` (of a phase, an angle) and ``pow`` (``|x|^c``, a fitted exponent): known,
priced, written by every back end, searched only where an input is an angle; real pyoperon and real
sparse regression recover ``-3·sin(θ)`` and a power law."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from physmend.config import ConfigError, compose
from physmend.symbolic import fit
from physmend.symbolic import _operon, _pysr
from physmend.symbolic._sindy import library
from physmend.config_check import KNOWN, OperatorError, check_operators
from physmend.symbolic.operators import operators_for, operon_symbols, priced_size, pysr_operators

DEFAULT = {"add": 1, "sub": 1, "mul": 1, "div": 1, "square": 1, "abs": 1, "sqrt": 1, "sin": 2, "cos": 2}
FAST = {"generations": 30, "population_size": 200}


@pytest.fixture(scope="module")
def shipped() -> dict[str, dict[str, int]]:
    """The shipped operator sets, composed once."""
    return {name: dict(compose([f"operators={name}"]).operators) for name in ("default", "extended")}


def _pendulum(n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An angle θ in rad over more than a half turn, an angular rate ω, and ``-3·sin(θ)`` (1/s²)."""
    rng = np.random.default_rng(seed)
    theta, omega = rng.uniform(-3.0, 3.0, n), rng.uniform(-2.0, 2.0, n)
    return np.column_stack([theta, omega]), -3.0 * np.sin(theta)


def test_sin_cos_and_pow_are_known_and_an_unknown_name_is_one_line_naming_it() -> None:
    assert {"sin", "cos", "pow"} <= set(KNOWN)
    assert check_operators({"add": 1, "sin": 2, "pow": 3}, "f.yaml") == {"add": 1, "sin": 2, "pow": 3}
    with pytest.raises(OperatorError) as info:
        check_operators({"add": 1, "sine": 2}, "my_ops.yaml")
    message = str(info.value)
    assert "\n" not in message and "my_ops.yaml" in message and "'sine'" in message and "sin, cos, pow" in message
    with pytest.raises(ConfigError) as info:
        compose(["+operators.cosinus=1"])
    assert "\n" not in str(info.value) and "'cosinus'" in str(info.value)


def test_sin_cos_and_pow_are_priced() -> None:
    theta, v, c = sp.Symbol("theta"), sp.Symbol("v"), sp.Float(-3.0)
    assert priced_size(c * sp.sin(theta), DEFAULT) == 1 + 1 + 2 + 1  # c, θ, sin, one product
    assert priced_size(c * sp.cos(theta), {**DEFAULT, "cos": 5}) == 1 + 1 + 5 + 1
    law = sp.Float(2.0) * sp.Abs(v) ** sp.Float(1.5)
    assert priced_size(law, {**DEFAULT, "pow": 2}) == 1 + 1 + 1 + 2 + 1  # c, v, exponent, pow, product
    assert priced_size(law, {**DEFAULT, "pow": 4}) == priced_size(law, {**DEFAULT, "pow": 2}) + 2
    # without the operators in the set: the price of an unlisted function, as before they were known
    plain = {k: p for k, p in DEFAULT.items() if k not in ("sin", "cos")}
    assert priced_size(c * sp.sin(theta), plain) == 1 + 1 + 3 + 1
    assert priced_size(law, plain) == 1 + (1 + 1) + 1 + 3 + 1  # c, |v| (v and abs), exponent, unlisted, product


def test_each_back_end_writes_them() -> None:
    ops = {**DEFAULT, "pow": 2}
    assert operon_symbols(ops).split(",")[-3:] == ["sin", "cos", "powabs"]
    pysr = pysr_operators(ops)
    assert {"sin", "cos"} <= set(pysr["unary_operators"]) and pysr["complexity_of_operators"]["sin"] == 2
    assert "powabs(x, y) = abs(x)^y" in pysr["binary_operators"] and pysr["complexity_of_operators"]["powabs"] == 2
    a, b = sp.symbols("a b")
    assert pysr["extra_sympy_mappings"]["powabs"](a, b) == sp.Abs(a) ** b and pysr["constraints"]["powabs"] == (-1, 1)
    n = 50
    X = np.column_stack([np.linspace(-3, 3, n), np.linspace(0, 90, n), np.linspace(1, 2, n), np.linspace(0, 1, n)])
    names = ["theta", "phi", "x", "soc"]
    labels = {t.label for t in library(X, names, {"theta": "rad", "phi": "deg", "x": "m", "soc": "1"}, operators=ops)}
    assert {"sin(theta)", "cos(theta)", "sin(pi*phi/180)", "cos(pi*phi/180)", "sin(soc)"} <= labels
    assert not any("(x)" in s and s.startswith(("sin", "cos")) for s in labels)  # x is a length: no phase


@pytest.mark.parametrize("units", [
    {"x": "m", "v": "m/s"},
    {"zone.T": "degC", "Q": "W", "UA": "W/K"},
    {"cell.soc": "1", "load.i": "A", "efficiency": "%"},  # unit-free ratios are no phase
    {"prey.x": "kanimals", "t": "1/tu", "unknown": ""},
    {},
])
def test_operators_for_leaves_the_set_unchanged_without_an_angle(units: dict[str, str],
                                                                 shipped: dict[str, dict[str, int]]) -> None:
    base = {"add": 1, "sub": 1, "mul": 1, "div": 1, "square": 1, "abs": 1, "sqrt": 1}
    for ops in shipped.values():
        assert operators_for(ops, units) == {k: p for k, p in ops.items() if k not in ("sin", "cos")}
    assert operators_for(shipped["default"], units) == base  # the seven operators of before


@pytest.mark.parametrize("unit", ["rad", "deg", "°", "rev"])
def test_operators_for_keeps_sin_and_cos_where_an_input_is_an_angle(unit: str,
                                                                    shipped: dict[str, dict[str, int]]) -> None:
    ops = shipped["default"]
    assert operators_for(ops, {"x": "m", "theta": unit}) == ops
    assert operators_for({**ops, "sin": None}, {"theta": unit})["sin"] is None  # switched off stays off


@pytest.mark.parametrize("unit, trig", [("rad", True), ("m", False)])
def test_each_back_end_searches_sin_and_cos_only_where_an_input_is_an_angle(unit: str, trig: bool) -> None:
    ops = {**DEFAULT, "pow": 2}
    names, units = ["theta", "x"], {"theta": unit, "x": "m"}
    operon = _operon.operator_settings(_operon.with_operators({"max_points": 10}, ops, set()), names, units)
    assert ("sin" in operon["allowed_symbols"].split(",")) is trig and "powabs" in operon["allowed_symbols"]
    assert "max_points" not in operon and _operon.SHARED not in operon
    mine = "add,sub,constant,variable"
    assert _operon.operator_settings(_operon.with_operators({}, ops, {"allowed_symbols"}) | {"allowed_symbols": mine},
                                     names, units)["allowed_symbols"] == mine  # the user's own symbols stay
    pysr = _pysr.operator_settings(_pysr.with_operators({"max_points": 10}, ops, set()), names, units)
    assert ({"sin", "cos"} <= set(pysr["unary_operators"])) is trig and "powabs" in pysr["constraints"]
    assert _pysr.SHARED not in pysr


def test_pyoperon_finds_minus_three_sin_theta() -> None:
    X, y = _pendulum()
    front = fit(X, y, ["theta", "omega"], units={"theta": "rad", "omega": "rad/s"}, operators=DEFAULT,
                options=FAST, seed=0)
    with_sin = [c for c in front.candidates if c.expr.has(sp.sin) and c.r2 > 0.99]
    assert with_sin, front.table()
    best = min(with_sin, key=lambda c: c.complexity)
    assert best.expr.free_symbols == {sp.Symbol("theta")}, best.text
    assert front.info["allowed_symbols"].endswith("sin,cos")


def test_without_an_angle_pyoperon_searches_without_sin() -> None:
    X, y = _pendulum(n=200)
    front = fit(X, y, ["theta", "omega"], units={"theta": "m", "omega": "m/s"}, operators=DEFAULT,
                options={"generations": 5, "population_size": 50}, seed=0)
    assert "sin" not in front.info["allowed_symbols"] and not any(c.expr.has(sp.sin, sp.cos) for c in front.candidates)


def test_the_sparse_library_finds_minus_three_sin_theta() -> None:
    X, y = _pendulum()
    front = fit(X, y, ["theta", "omega"], backend="sindy", units={"theta": "rad", "omega": "rad/s"}, operators=DEFAULT)
    best = min((c for c in front.candidates if c.r2 > 0.999), key=lambda c: c.complexity)
    assert sp.simplify(best.expr - sp.Float(-3.0) * sp.sin(sp.Symbol("theta"))).is_zero or \
        abs(float(sp.expand(best.expr).coeff(sp.sin(sp.Symbol("theta")))) + 3.0) < 1e-6, best.text


def test_pyoperon_finds_a_power_law_with_a_fitted_exponent() -> None:
    rng = np.random.default_rng(1)
    v, x = rng.uniform(-2.0, 2.0, 400), rng.uniform(0.5, 2.0, 400)
    y = 2.0 * np.abs(v) ** 1.5
    ops = {"add": 1, "sub": 1, "mul": 1, "div": 1, "pow": 2}
    front = fit(np.column_stack([v, x]), y, ["v", "x"], operators=ops, options=FAST, seed=1)
    good = [c for c in front.candidates if c.r2 > 0.9999]
    assert good, front.table()
    best = min(good, key=lambda c: c.complexity)
    powers = [p for p in best.expr.atoms(sp.Pow) if isinstance(p.base, sp.Abs)]
    assert powers and abs(float(powers[0].exp) - 1.5) < 0.01, best.text
    assert best.complexity == priced_size(best.expr, ops)
