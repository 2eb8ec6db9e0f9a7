"""The mechanism catalogue and interval-scale quantities (°C): no form that uses a temperature in °C
other than linearly or as a difference is proposed or used to name a mechanism."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from physmend.explain.catalogue import load_catalogue
from physmend.explain.mechanisms import classify
from physmend.symbolic.choice import catalogue_candidates
from physmend.modeling.interval import interval_violation

T1, T2, FLOW = "zone1.air.T", "zone2.air.T", "fan.flow"
A, B, U = (sympy.Symbol(n) for n in (T1, T2, FLOW))
CELSIUS = {T1: "degC", T2: "degC", FLOW: "m3/s"}
KELVIN = {T1: "K", T2: "K", FLOW: "m3/s"}


@pytest.fixture(scope="module")
def samples() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    n = 800
    t1 = rng.uniform(-25.0, 8.0, n)  # both signs: |T| and sign(T) have a shape here
    return {T1: t1, T2: t1 - rng.uniform(-15.0, 25.0, n), FLOW: rng.uniform(0.05, 0.6, n)}


def test_torricelli_is_not_named_for_a_celsius_quantity(samples):
    expr = 5.1 * sympy.sqrt(sympy.Abs(A))
    named = {m.id for m in classify(expr, samples, CELSIUS, top=20)}
    assert "orifice_outflow" not in named and "power_law" not in named
    # the same values in a unit without an offset: the form is the orifice's
    assert classify(expr, samples, {T1: "m"}, top=1)[0].id == "orifice_outflow"


@pytest.mark.parametrize("expr, refused", [
    (-0.56 * sympy.sign(A), "coulomb_friction"),
    (0.3 * A * sympy.Abs(A), "quadratic_drag"),
    (0.01 * A ** 3, "cubic"),
    (0.2 * A * B, "interaction"),
])
def test_no_form_breaking_the_rule_names_a_celsius_formula(expr, refused, samples):
    matches = classify(expr, samples, CELSIUS, top=30)
    assert refused not in {m.id for m in matches}
    for m in matches:
        entry = next(e for e in load_catalogue() if e.id == m.id)
        assert entry.interval_reason(m.variables, CELSIUS) is None, m


def test_a_celsius_difference_is_still_named_buoyancy_leakage(samples):
    d = A - B
    top = classify(1.7 * d * sympy.sqrt(sympy.Abs(d)), samples, CELSIUS, top=1)[0]
    assert top.id == "buoyancy_leakage" and top.r2 > 0.999 and abs(top.coefficient - 1.7) < 1e-6


def test_catalogue_candidates_for_celsius_inputs_never_break_the_rule(samples):
    d = samples[T1] - samples[T2]
    y = 0.9 * d * np.sqrt(np.abs(d))
    inputs = [T1, T2, FLOW]
    cands = catalogue_candidates(inputs, CELSIUS, samples, y)
    assert cands
    thresholds = {m.name for m in load_catalogue() if m.k == "threshold"}
    for c in cands:
        if any(f"[catalogue: {name}" in c.text for name in thresholds):
            continue  # its k is a value on the variable's own scale (a quantile of it): it moves with the zero
        assert interval_violation(c.expr, CELSIUS) is None, c.text
    texts = " ".join(c.text for c in cands if FLOW not in {str(x) for x in c.expr.free_symbols})
    for name in ("orifice", "Coulomb", "cubic", "quadratic drag", "interaction", "radiation", "power law"):
        assert name not in texts  # of a temperature in °C (the flow may take them)
    assert "orifice" in " ".join(c.text for c in cands)  # √|fan.flow|: a flow has a true zero
    best = min(cands, key=lambda c: c.mse)
    assert "buoyancy-driven leakage" in best.text and best.r2 > 0.9999
    # threshold forms move with the zero of their variable: still offered for a °C quantity
    assert "overflow" in texts and "saturation" in texts
    # in kelvin the same inputs may take every form (the catalogue's own unit rules aside)
    kelvin = {k: v + (273.15 if KELVIN[k] == "K" else 0.0) for k, v in samples.items()}
    k_texts = " ".join(c.text for c in catalogue_candidates([T1, T2], KELVIN, kelvin, y))
    assert "orifice" in k_texts and "interaction" in k_texts


def test_the_interval_rule_of_each_shipped_form():
    by_id = {m.id: m for m in load_catalogue()}
    one = {"u": T1}
    two = {"a": T1, "b": T2}
    for ident in ("coulomb_friction", "orifice_outflow", "quadratic_drag", "cubic", "power_law", "saturable_rate"):
        assert not by_id[ident].admissible(one, CELSIUS), ident
    for ident in ("gain", "saturation", "overflow"):
        assert by_id[ident].admissible(one, CELSIUS), ident
    for ident in ("conductance", "buoyancy_leakage", "quadratic_exchange", "limited_by_smaller", "one_way_exchange"):
        assert by_id[ident].admissible(two, CELSIUS), ident
    assert not by_id["interaction"].admissible(two, CELSIUS)
    assert by_id["interaction"].admissible(two, KELVIN)
    assert by_id["scaled_gain"].admissible({"b": FLOW, "u": T1}, CELSIUS)
    assert by_id["modulated_conductance"].admissible({"u": FLOW, **two}, CELSIUS)
    reason = by_id["orifice_outflow"].interval_reason(one, CELSIUS)
    assert reason is not None and "degC" in reason
