"""Mechanism catalogue: loading and validation, numerical classification of formulas."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from physmend.explain.catalogue import DEFAULT_CATALOGUE, CatalogueError, MechanismError, load_catalogue
from physmend.explain.mechanisms import MechanismMatch, classify

T1, T2, PRESS, FLOW = "zone1.air.T", "ambient.T", "zone1.air.p", "fan.flow"
A, B, P, U = (sympy.Symbol(n) for n in (T1, T2, PRESS, FLOW))
UNITS = {T1: "K", T2: "K", PRESS: "Pa", FLOW: "m3/s"}


@pytest.fixture(scope="module")
def samples() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    n = 600
    return {
        T1: rng.uniform(250.0, 400.0, n),
        T2: rng.uniform(250.0, 400.0, n),
        PRESS: rng.uniform(0.99e5, 1.02e5, n),
        FLOW: rng.uniform(0.0, 0.5, n),
    }


def test_shipped_catalogue_is_valid_and_generic():
    catalogue = load_catalogue()
    ids = [m.id for m in catalogue]
    assert {"conductance", "buoyancy_leakage", "quadratic_exchange", "radiation", "gain", "steady_source"} <= set(ids)
    assert len(ids) == len(set(ids))
    for m in catalogue:
        assert set(m.placeholders) <= {"a", "b", "u"}  # placeholders, never model variables
    assert load_catalogue(DEFAULT_CATALOGUE)[0].id == ids[0]


@pytest.mark.parametrize(
    "expr",
    [
        1.3 * (A - B) * sympy.sqrt(sympy.Abs(A - B)),
        sympy.sign(A - B) * sympy.Abs(A - B) ** 1.5,  # algebraically rewritten, same function
        -2.0 * (B - A) * sympy.sqrt(sympy.Abs(B - A)) + 1e-6,
    ],
    ids=["canonical", "sign-abs-pow", "swapped"],
)
def test_leakage_form_is_buoyancy_leakage(expr, samples):
    matches = classify(expr, samples, UNITS)
    top = matches[0]
    assert isinstance(top, MechanismMatch)
    assert top.id == "buoyancy_leakage" and top.r2 > 0.99
    assert set(top.variables.values()) == {T1, T2}
    assert top.coefficient > 0  # a - b oriented so that c is positive
    assert T1 in top.explanation and T2 in top.explanation and "leakage" in top.explanation
    assert "{" not in top.explanation
    assert len(matches) == 3 and matches[1].r2 <= top.r2


def test_leakage_coefficient_and_formula(samples):
    top = classify(1.3 * (A - B) * sympy.sqrt(sympy.Abs(A - B)), samples, UNITS)[0]
    assert top.variables == {"a": T1, "b": T2}
    assert top.coefficient == pytest.approx(1.3)
    assert top.formula == f"1.3*({T1} - {T2})*sqrt(|{T1} - {T2}|)"


def test_linear_difference_is_conductance(samples):
    top = classify(0.7 * A - 0.7 * B + 0.001, samples, UNITS)[0]
    assert top.id == "conductance" and top.r2 > 0.99
    assert set(top.variables.values()) == {T1, T2}
    assert top.coefficient == pytest.approx(0.7, rel=1e-3)


def test_fourth_powers_in_kelvin_are_radiation(samples):
    top = classify(5.67e-8 * (A**4 - B**4), samples, UNITS)[0]
    assert top.id == "radiation" and top.r2 > 0.999
    assert top.coefficient == pytest.approx(5.67e-8, rel=1e-6)
    # the same form in degC is not absolute temperature: never radiation
    units_c = {**UNITS, T1: "degC", T2: "degC"}
    assert all(m.id != "radiation" for m in classify(5.67e-8 * (A**4 - B**4), samples, units_c, top=10))


def test_quadratic_exchange(samples):
    top = classify(0.2 * (B - A) * sympy.Abs(A - B), samples, UNITS)[0]
    assert top.id == "quadratic_exchange" and top.r2 > 0.999


def test_constant_is_steady_source(samples):
    top = classify(sympy.Float(-42.0), samples, UNITS)[0]
    assert top.id == "steady_source" and top.r2 == pytest.approx(1.0)
    assert top.coefficient == pytest.approx(-42.0)


def test_input_proportional_is_gain(samples):
    top = classify(3.0 * U, samples, UNITS)[0]
    assert top.id == "gain" and top.variables == {"u": FLOW} and top.r2 > 0.999


def test_modulated_conductance(samples):
    top = classify(0.3 * U * (A - B), samples, UNITS)[0]
    assert top.id == "modulated_conductance" and top.variables["u"] == FLOW and top.r2 > 0.999


@pytest.mark.parametrize("expr, mechanism, k", [
    (-40.0 * U / (0.05 + U), "saturable_rate", 0.05),            # Michaelis-Menten: the scale fitted
    (3.0 * sympy.Min(U, 0.3), "saturation", 0.3),               # a limit inside the range
    (0.8 * sympy.Max(U - 0.2, 0), "overflow", 0.2),              # acts above a threshold
    (-0.3 * U * sympy.Abs(U), "quadratic_drag", None),
    (5.0 * U**3, "cubic", None),
    (1.5 * U * sympy.Abs(U) ** 0.7, "power_law", 1.7),          # the exponent fitted
    (3.0 * sympy.Min(A, B), "limited_by_smaller", None),
    (0.4 * sympy.Max(A - B, 0), "one_way_exchange", None),
], ids=["michaelis-menten", "saturation", "overflow", "drag", "cubic", "power", "min-of-two", "one-way"])
def test_each_form_with_its_constants_is_named(expr, mechanism, k, samples):
    top = classify(expr, samples, UNITS)[0]
    assert top.id == mechanism and top.r2 > 0.9999, (top.id, top.r2)
    if k is not None:
        assert top.k == pytest.approx(k, rel=1e-3)
        assert f"{k:.4g}" in top.formula


def test_different_units_are_never_paired(samples):
    units_by_var = UNITS
    expr = 0.7 * (A - P)  # kelvin minus pascal: no physical difference
    matches = classify(expr, samples, UNITS, top=50)
    catalogue = {m.id: m for m in load_catalogue()}
    for match in matches:
        for group in catalogue[match.id].same_unit:
            assert len({units_by_var[match.variables[p]] for p in group}) == 1
        assert not ({"a", "b"} <= set(match.variables) and {match.variables["a"], match.variables["b"]} == {T1, PRESS})
    # a variable without a unit is never paired either
    no_units = classify(0.7 * (A - B), samples, {PRESS: "Pa"}, top=50)
    assert all("a" not in m.variables for m in no_units)


def test_custom_catalogue_is_data(tmp_path, samples):
    path = tmp_path / "mine.yaml"
    path.write_text(
        "mechanisms:\n"
        "  - id: product\n"
        "    name: product of two inputs\n"
        "    template: c*a*b\n"
        "    explanation: 'an interaction between {a} and {b}'\n"
    )
    top = classify(2.5 * A * U, samples, UNITS, catalogue_path=path)[0]
    assert top.id == "product" and top.r2 > 0.999 and set(top.variables.values()) == {T1, FLOW}
    assert top.explanation in (f"an interaction between {T1} and {FLOW}", f"an interaction between {FLOW} and {T1}")


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ("  - id: x\n    name: n\n    template: c*a\n", "must have the keys ['id', 'name', 'template', 'explanation'], but ['explanation'] are missing"),
        ("  - id: x\n    name: n\n    template: c*a + a\n    explanation: e\n", "template must be 'c' times an expression of the placeholders"),
        ("  - id: x\n    name: n\n    template: a - b\n    explanation: e\n", "template must contain the coefficient 'c'"),
        ("  - id: x\n    name: n\n    template: c*a\n    explanation: 'from {z}'\n", "explanation may only use the placeholders ['a'] as {fields}, but uses ['z']"),
        ("  - id: x\n    name: n\n    template: c*a\n    same_unit: [[a, q]]\n    explanation: e\n", "same_unit names ['q'], which are not placeholders"),
        ("  - id: x\n    name: n\n    template: c*a\n    explanation: e\n    colour: red\n", "unknown ['colour']"),
        ("  - id: x\n    name: n\n    template: c*a\n    explanation: e\n  - id: x\n    name: m\n    template: c\n    explanation: f\n", "ids must be unique, but entries 0 and 1 are both 'x'"),
        ("  - id: x\n    name: n\n    template: 'c*(a'\n    explanation: e\n", "template must be a sympy expression"),
        ("  - id: x\n    name: n\n    template: c*Min(a, k)\n    k: level\n    explanation: e\n", "k must be one of ['threshold', 'scale', 'exponent']"),
        ("  - id: x\n    name: n\n    template: c*Min(a, b)\n    k: threshold\n    explanation: e\n", "must hold the constant 'k' and a placeholder"),
        ("  - id: x\n    name: n\n    template: c*b*Min(a, k)\n    k: threshold\n    explanation: e\n", "needs k_of: the placeholder whose samples set the grid"),
        ("  - id: x\n    name: n\n    template: c*b*Min(a, k)\n    k: threshold\n    k_of: z\n    explanation: e\n", "k_of must be one of the placeholders ['a', 'b'], but got 'z'"),
        ("  - id: x\n    name: n\n    template: c*b*a\n    k_of: a\n    explanation: e\n", "so it needs k, but the entry has no k"),
    ],
    ids=["missing-key", "not-linear-in-c", "no-c", "bad-field", "bad-unit-group", "unknown-key", "duplicate", "unparsable",
         "bad-k-grid", "k-missing", "k_of-missing", "k_of-unknown", "k_of-without-k"],
)
def test_bad_catalogue_names_file_and_entry(tmp_path, entry, message):
    path = tmp_path / "bad.yaml"
    path.write_text("mechanisms:\n" + entry)
    with pytest.raises(CatalogueError) as err:
        load_catalogue(path)
    text = str(err.value)
    assert str(path) in text and message in text
    if "unique" not in message:
        assert "mechanism entry 0 (id 'x')" in text


def test_unreadable_catalogue(tmp_path):
    with pytest.raises(CatalogueError, match="cannot read"):
        load_catalogue(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("mechanisms: [\n")
    with pytest.raises(CatalogueError, match="not valid YAML"):
        load_catalogue(bad)


def test_classify_bad_input(samples):
    with pytest.raises(MechanismError, match=r"none were given for \['other.T'\]"):
        classify(A - sympy.Symbol("other.T"), samples, UNITS)
    with pytest.raises(MechanismError, match="one length"):
        classify(A - B, {T1: np.ones(5), T2: np.ones(6)}, UNITS)
    with pytest.raises(MechanismError, match="top must be an integer >= 1, but got 0"):
        classify(A - B, samples, UNITS, top=0)


def test_a_form_outside_the_catalogue_matches_nothing(samples):
    """A formula none of the catalogue's forms can reproduce gets no mechanism at the report's bar
    (propose.MIN_MECHANISM_R2): the report then says so plainly and shows the formula."""
    from physmend.proposal import MIN_MECHANISM_R2

    odd = sympy.sin((A - B) / 7.0) * sympy.exp(-U * 4.0) * P / 1e5
    matches = classify(odd, samples, UNITS)
    assert all(m.r2 < MIN_MECHANISM_R2 for m in matches), [(m.id, round(m.r2, 3)) for m in matches[:3]]
    # while the catalogue's own form, sized anyhow, is named
    assert classify(-2.5 * (A - B), samples, UNITS)[0].r2 > 0.999


@pytest.mark.parametrize(
    ("truth", "expected"),
    [
        # Froelich: an emf proportional to speed w through a flux that saturates with the current i
        (lambda w, i: -0.5 * w * i**2 / (3.0 + i), "scaled_saturating_linear"),
        # Monod: growth proportional to biomass X on a saturating substrate S
        (lambda w, i: 0.8 * w * i / (0.4 + i), "scaled_saturable_rate"),
    ],
    ids=["saturating-linear-law-times-speed", "monod-times-biomass"],
)
def test_a_saturating_form_scaled_by_a_second_quantity_is_named(truth, expected):
    """A catalogue form with a second constant may hold several placeholders (``k_of`` names the
    one that sizes the grid of k): a saturation in one quantity scaled by another is recognised, with
    its constants, wherever the two quantities have different units."""
    rng = np.random.default_rng(3)
    b = rng.uniform(100.0, 180.0, 400)   # rad/s (or g/L of biomass)
    u = rng.uniform(0.2, 3.0, 400)       # A (or g/L of substrate)
    units = {"b": "rad/s", "u": "A"}
    y = truth(b, u)
    expr = sympy.Symbol("b") * sympy.Symbol("u") ** 2 / (3 + sympy.Symbol("u")) if expected.startswith("scaled_sat") \
        and "linear" in expected else sympy.Symbol("b") * sympy.Symbol("u") / (sympy.Rational(2, 5) + sympy.Symbol("u"))
    matches = classify(expr, {"b": b, "u": u}, units, top=3)
    assert matches[0].id == expected and matches[0].r2 > 0.9999, matches
    assert matches[0].variables == {"b": "b", "u": "u"}
    from physmend.symbolic.choice import catalogue_candidates

    found = catalogue_candidates(["b", "u"], units, {"b": b, "u": u}, y)
    best = max(found, key=lambda c: c.r2)
    assert best.r2 > 0.9999 and expected.replace("_", " ").split()[-1] in best.text.lower() or best.r2 > 0.9999, best.text
    same = [c for c in found if c.r2 > 0.9999 and "offset" not in c.text]
    assert same and all(len(c.expr.free_symbols) == 2 for c in same), [c.text for c in same]
    # the same unit for both: no scaled form is offered (different_unit)
    assert not [c for c in catalogue_candidates(["b", "u"], {"b": "A", "u": "A"}, {"b": b, "u": u}, y)
                if "scaled by a second" in c.text]
