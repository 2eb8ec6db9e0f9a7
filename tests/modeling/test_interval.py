"""Interval-scale quantities (°C) in formulas: refused inside nonlinear operators and products, accepted
as differences and linearly; fit() with real pyoperon drops and counts the formulas that break the rule."""

from __future__ import annotations

import time

import numpy as np
import pytest
import sympy as sp

from physmend.symbolic import fit
from physmend.modeling.interval import MAX_NODES, interval_violation, shift_violation

T1, T2, TF, u, K1 = sp.symbols("zone1.air.T zone2.air.T plant.TF fan.flow wall.T")
UNITS = {"zone1.air.T": "degC", "zone2.air.T": "degC", "plant.TF": "degF", "fan.flow": "m3/s", "wall.T": "K"}


@pytest.mark.parametrize("expr, where", [
    (-0.56 * sp.sign(T1), "sign("),
    (5.1 * sp.sqrt(sp.Abs(T1)), "|zone1.air.T|"),
    ((-0.99 * T2 + 0.72 * T1) ** 2 + 22.4, "the base"),
    ((T1 - 0.72 * T2) ** 2, "the base"),
    (2.0 * T1 * sp.sqrt(sp.Abs(T1)), "|zone1.air.T|"),
    (T1 ** 2, "the base"),
    (1 / T1, "the base"),
    (3.0 * T1 * T2, "product of"),
    (T1 * (T1 + T2), "product of"),
    (sp.exp(0.1 * T1), "exp("),
    (sp.tanh(T2), "tanh("),
    (sp.cos(T1), "cos("),
    (sp.Max(T1 - 3.0, 0), "compares"),
    (sp.Heaviside(T1), "Heaviside("),
    (sp.sqrt(sp.Abs(T1 - TF)), "plant.TF"),  # °C and °F: two zeros, no difference
])
def test_an_interval_scale_quantity_is_refused_inside_nonlinear_operators(expr: sp.Expr, where: str) -> None:
    why = interval_violation(expr, UNITS)
    assert why is not None and where in why and len(why) <= 100, why


@pytest.mark.parametrize("expr", [
    1.3 * (T1 - T2) * sp.Abs(T1 - T2),
    1.3 * (T1 - T2) * sp.sqrt(sp.Abs(T1 - T2)),
    0.8 * (T1 - T2) + 0.1 * T1,
    2.0 * T1 * u,                                 # enthalpy carried by a flow: linear in T
    T1 * (T1 - T2),                               # a difference is a ratio-scale quantity, like a flow
    0.4 * u * (T1 - T2) ** 2,
    sp.sign(T1 - T2) * u,
    sp.exp(-0.1 * (T1 - T2)),
    sp.Min(T1, T2),                                # moves with the zero as T does
    sp.Max(T1 - T2, 0),
    2.5 * u * T1 - 2.5 * u * T2 + sp.sqrt(sp.Abs(3.0 * T1 - 3.0 * T2)),
    K1 ** 4 - 2.0 * K1 * u,                        # kelvin: an absolute scale, unaffected
    sp.sign(u) * sp.sqrt(sp.Abs(u)),
    sp.Integer(3),
])
def test_differences_linear_terms_and_absolute_units_are_accepted(expr: sp.Expr) -> None:
    assert interval_violation(expr, UNITS) is None


def test_symbols_without_a_unit_are_unaffected() -> None:
    assert interval_violation(sp.sign(T1) * T1 * T2, {}) is None
    assert interval_violation(sp.sign(T1), {"zone1.air.T": ""}) is None


def test_a_declared_affine_unit_is_subject_to_the_rule(monkeypatch: pytest.MonkeyPatch) -> None:
    from physmend.modeling import Model
    from physmend.modeling import units as units_module

    monkeypatch.setattr(units_module, "_USER_AFFINE", {})
    monkeypatch.setattr(units_module, "_USER_BASE", {})
    x, y = sp.symbols("a.T b.T")
    units = {"a.T": "degRe", "b.T": "degRe"}
    assert interval_violation(sp.sqrt(sp.Abs(x)), units) is None  # not yet declared: an ordinary word
    Model("m").affine_unit("degRe", offset=218.52, base="K")
    assert "|a.T|" in (interval_violation(sp.sqrt(sp.Abs(x)), units) or "")
    assert interval_violation(sp.sqrt(sp.Abs(x - y)), units) is None


def test_the_check_is_fast_and_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    exprs = [sp.Float(0.3 + 0.01 * i) * (T1 - T2) * sp.sqrt(sp.Abs(T1 - T2)) + sp.Float(i) * u * T1
             + (T1 - sp.Float(0.7 + 0.001 * i) * T2) ** 2 for i in range(100)]
    start = time.perf_counter()
    verdicts = [interval_violation(e, UNITS) for e in exprs]
    assert all(v is not None and "the base" in v for v in verdicts)
    assert time.perf_counter() - start < 5.0  # milliseconds each (2 busy cores: generous)
    from physmend.modeling import interval

    monkeypatch.setattr(interval, "MAX_NODES", 40)  # a formula larger than the bound is refused unread
    huge = sp.Add(*[sp.Float(k + 1.5) * sp.Abs(T1 - T2) ** k for k in range(2, 12)])
    why = shift_violation(huge, {T1: "degC", T2: "degC"})
    assert why is not None and "too large" in why and "> 40" in why
    assert MAX_NODES >= 1000  # symbolic regression's formulas (tens of nodes) are always read


def _celsius_data(n: int = 400, seed: int = 1) -> tuple[np.ndarray, np.ndarray, list[str]]:
    rng = np.random.default_rng(seed)
    t1 = rng.uniform(-25.0, 5.0, n)           # °C: both signs, so sign(T) and |T| look like shapes
    t2 = t1 - rng.uniform(-20.0, 20.0, n)
    flow = rng.uniform(0.1, 1.0, n)
    d = t1 - t2
    y = 0.8 * d * np.sqrt(np.abs(d)) + 0.5 * flow * t1
    return np.stack([t1, t2, flow], axis=1), y, ["zone1.air.T", "zone2.air.T", "fan.flow"]


def test_fit_with_operon_drops_and_counts_interval_violations() -> None:
    X, y, names = _celsius_data()
    units = {"zone1.air.T": "degC", "zone2.air.T": "degC", "fan.flow": "m3/s"}
    opts = {"generations": 15, "population_size": 200, "max_time": 20}
    front = fit(X, y, names, backend="operon", units=units, seed=0, options=opts)
    assert front.info["interval_rejected"] > 0, front.info
    print(front.info["interval_rejected"], "of", front.info["n_raw_candidates"], front.info["interval_rejected_examples"])
    assert len(front.info["interval_rejected_examples"]) == min(3, front.info["interval_rejected"])
    for c in front.candidates:
        assert interval_violation(c.expr, units) is None, c.text
    # the same search with the temperatures in kelvin: nothing is refused for that reason
    kelvin = fit(X + np.array([273.15, 273.15, 0.0]), y, names, backend="operon", seed=0, options=opts,
                 units={"zone1.air.T": "K", "zone2.air.T": "K", "fan.flow": "m3/s"})
    assert kelvin.info["interval_rejected"] == 0
    # the check goes with the units check
    free = fit(X, y, names, backend="operon", units=units, seed=0, options=opts, check_units=False)
    assert free.info["interval_rejected"] == 0
