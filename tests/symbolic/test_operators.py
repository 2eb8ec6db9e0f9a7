"""Operators as data (the ``operators`` config group), shared by the back ends: each family recovers a
known formula from simulated data with real pyoperon and real sparse regression; prices make one
complexity for every back end; a bad operators file is one line naming the file and the entry."""

from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from physmend.config import ConfigError, compose
from physmend.symbolic import fit
from physmend.config_check import check_operators
from physmend.symbolic.operators import operon_symbols, priced_size, pysr_operators

DEFAULT = {"add": 1, "sub": 1, "mul": 1, "div": 1, "square": 1, "abs": 1, "sqrt": 1}
EXTENDED = {**DEFAULT, "sign": 2, "min": 2, "max": 2, "exp": 2, "log": 2, "tanh": 2}
FAST = {"generations": 30, "population_size": 200}


def _data(n: int = 600, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"x": rng.uniform(-2, 2, n), "y": rng.uniform(0.5, 3, n), "area": rng.choice([3.0, 6.0, 9.0], n),
            "sun": rng.uniform(0, 800, n)}


def _best(front, min_r2: float = 0.99):  # noqa: ANN001, ANN202
    ok = [c for c in front.candidates if c.r2 >= min_r2]
    assert ok, front.table()
    return min(ok, key=lambda c: c.complexity)


def test_the_shipped_operator_files_compose_and_are_checked() -> None:
    cfg = compose(["operators=extended"])
    assert check_operators(dict(cfg.operators), "x") == {**EXTENDED, "sin": 2, "cos": 2, "pow": 2}
    assert dict(compose([]).operators) == {**DEFAULT, "sin": 2, "cos": 2}  # sin, cos: only of an angle


@pytest.mark.parametrize("override, words", [
    (["+operators.cosine=1"], ["operators", "default.yaml", "unknown operator 'cosine'"]),
    (["operators.mul=-1"], ["default.yaml", "price of 'mul'", "-1"]),
    (["operators.mul=1.5"], ["price of 'mul'", "1.5"]),
])
def test_a_bad_operator_entry_is_one_line_naming_the_file_and_entry(override: list[str], words: list[str]) -> None:
    with pytest.raises(ConfigError) as info:
        compose(override)
    message = str(info.value)
    assert "\n" not in message and all(w in message for w in words), message


def test_prices_make_one_complexity_for_every_back_end() -> None:
    dt = sp.Symbol("a") - sp.Symbol("b")
    leak = sp.Symbol("c1") * dt * sp.sqrt(sp.Abs(dt))
    assert priced_size(leak, DEFAULT) == 10  # c1, (a - b) twice (3 each), sqrt, two products
    assert priced_size(leak, {**DEFAULT, "sqrt": 4}) == priced_size(leak, DEFAULT) + 3
    friction = sp.Float(-0.6) * sp.sign(sp.Symbol("v"))
    assert priced_size(friction, EXTENDED) == 1 + 1 + 2 + 1  # c, v, sign, one product
    assert operon_symbols(EXTENDED) == "constant,variable,add,sub,mul,div,square,abs,sqrtabs,fmin,fmax,exp,logabs,tanh"
    pysr = pysr_operators(EXTENDED)
    assert pysr["binary_operators"] == ["+", "-", "*", "/", "min", "max"]
    assert "sign" in pysr["unary_operators"] and pysr["complexity_of_operators"]["sign"] == 2


def test_operon_searches_only_with_the_listed_operators() -> None:
    d = _data()
    X = np.column_stack([d["x"], d["y"]])
    target = 0.7 * d["x"] * np.sqrt(np.abs(d["x"]))
    front = fit(X, target, ["x", "y"], operators={"add": 1, "mul": 1, "sub": 1}, options=FAST, seed=1)
    used = set().union(*(c.expr.atoms(sp.Function, sp.Pow) for c in front.candidates))
    assert not any(isinstance(a, (sp.Abs,)) or (a.is_Pow and not a.exp.is_Integer) for a in used), used
    # every candidate is priced by the shared rule
    assert all(c.complexity == priced_size(c.expr, {"add": 1, "mul": 1, "sub": 1}) for c in front.candidates)


def test_a_product_of_two_states_is_recovered_by_both_back_ends() -> None:
    d = _data()
    X = np.column_stack([d["x"], d["y"]])
    target = -0.5 * d["x"] * d["y"] + np.random.default_rng(3).normal(0, 0.01, d["x"].size)
    for backend, options in (("operon", FAST), ("sindy", {})):
        best = _best(fit(X, target, ["x", "y"], backend=backend, operators=DEFAULT, options=options, seed=0))
        xy = sp.Symbol("x") * sp.Symbol("y")
        expanded = sp.expand(best.expr)
        assert abs(float(expanded.coeff(xy)) + 0.5) < 0.01, (backend, best.text)
        rest = expanded - expanded.coeff(xy) * xy  # at most a noise-sized offset
        assert rest.free_symbols == set() and abs(float(rest)) < 0.01, (backend, best.text)


def test_a_parameter_times_an_input_is_recovered() -> None:
    d = _data()
    X = np.column_stack([d["area"], d["sun"]])
    target = 0.6 * d["area"] * d["sun"]
    best = _best(fit(X, target, ["area", "sun"], backend="sindy", operators=DEFAULT))
    coef = sp.simplify(best.expr / (sp.Symbol("area") * sp.Symbol("sun")))
    assert coef.is_Number and abs(float(coef) - 0.6) < 1e-3, best.text


def test_signed_friction_is_recovered_with_sign() -> None:
    d = _data()
    X = np.column_stack([d["x"], d["y"]])
    target = -0.6 * np.sign(d["x"]) + np.random.default_rng(4).normal(0, 0.01, d["x"].size)
    best = _best(fit(X, target, ["x", "y"], backend="sindy", operators=EXTENDED), min_r2=0.995)
    assert best.expr.has(sp.sign) and best.expr.free_symbols == {sp.Symbol("x")}, best.text
    without = fit(X, target, ["x", "y"], backend="sindy", operators=DEFAULT)
    assert not any(c.expr.has(sp.sign) for c in without.candidates)


def test_saturation_is_recovered_with_min() -> None:
    d = _data()
    X = np.column_stack([d["x"], d["y"]])
    target = 3.0 * np.minimum(d["x"], d["y"])  # a flow limited by whichever of two is smaller
    best = _best(fit(X, target, ["x", "y"], backend="sindy", units={"x": "m", "y": "m"}, operators=EXTENDED), min_r2=0.999)
    assert best.expr.has(sp.Min), best.text
    front = fit(X, target, ["x", "y"], operators=EXTENDED, options=FAST, seed=0)
    assert _best(front, min_r2=0.999).expr.has(sp.Min), front.table()


def test_a_constant_source_is_a_constant() -> None:
    d = _data()
    X = np.column_stack([d["x"], d["y"]])
    target = -0.15 + np.random.default_rng(5).normal(0, 0.002, d["x"].size)
    front = fit(X, target, ["x", "y"], backend="sindy", operators=DEFAULT)
    simplest = front.candidates[0]
    assert simplest.expr.is_Number and abs(float(simplest.expr) + 0.15) < 1e-3, front.table()
