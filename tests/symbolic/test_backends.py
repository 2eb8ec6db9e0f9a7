"""Symbolic regression back ends (real pyoperon and pysindy), Pareto choice and serialisation."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
import sympy

from physmend.explain.mechanisms import classify
from physmend.symbolic import (
    BackendUnavailable,
    Candidate,
    ParetoFront,
    SymbolicError,
    available_backends,
    choose,
    evaluate,
    fit,
    fit_many,
    mse_r2,
    prepare,
)
from physmend.symbolic._sindy import library

NAMES = ["zone1.air.T", "ambient.T", "fan.flow"]
UNITS = {"zone1.air.T": "K", "ambient.T": "K", "fan.flow": "m3/s"}
A, B, U = (sympy.Symbol(n) for n in NAMES)


def leakage(a, b):
    d = a - b
    return 1.3 * d * np.sqrt(np.abs(d))


def linear(a, b):
    return 0.7 * (a - b)


def make_data(law, *, n: int = 3000, seed: int = 0, noise: float = 0.01):
    """Inputs (two temperatures in K and a distractor flow) and the law plus ``noise`` relative noise."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(275.0, 305.0, n)
    b = rng.uniform(275.0, 305.0, n)
    u = rng.uniform(0.0, 0.5, n)
    y = law(a, b)
    y = y + noise * np.std(y) * rng.standard_normal(n)
    return np.column_stack([a, b, u]), y


def fresh_r2(expr: sympy.Expr, law) -> float:
    X, _ = make_data(law, n=2000, seed=12345, noise=0.0)
    truth = law(X[:, 0], X[:, 1])
    pred = evaluate(expr, {n: X[:, j] for j, n in enumerate(NAMES)})
    return mse_r2(truth, pred)[1]


def test_available_backends_here():
    backends = available_backends()
    assert "operon" in backends and "sindy" in backends


@pytest.mark.parametrize("law", [leakage, linear], ids=["leakage", "linear"])
def test_operon_recovers_law(law):
    X, y = make_data(law)
    start = time.perf_counter()
    front = fit(X, y, NAMES, backend="operon", units=UNITS, target="zone1.air.T", seed=0)
    seconds = time.perf_counter() - start
    assert seconds < 30
    assert front.backend == "operon" and front.inputs == NAMES and front.n_points == 3000
    assert front.info["n_points_search"] == 2000  # subsampled deterministically
    complexities = [c.complexity for c in front.candidates]
    mses = [c.mse for c in front.candidates]
    assert complexities == sorted(complexities) and mses == sorted(mses, reverse=True)
    i, why = choose(front)
    chosen = front.candidates[i]
    assert "knee" in why and "5%" in why
    assert chosen.r2 >= 0.99
    assert fresh_r2(chosen.expr, law) >= 0.99
    assert {s.name for s in chosen.expr.free_symbols} <= set(NAMES)
    # The chosen formula reads as the right mechanism.
    samples = {n: X[:, j] for j, n in enumerate(NAMES)}
    top = classify(chosen.expr, samples, UNITS)[0]
    assert top.id == ("buoyancy_leakage" if law is leakage else "conductance")
    assert set(top.variables.values()) == {"zone1.air.T", "ambient.T"}
    assert top.r2 > 0.99


def test_operon_is_deterministic_for_a_seed():
    X, y = make_data(linear, n=500)
    f1 = fit(X, y, NAMES, backend="operon", units=UNITS, seed=3, options={"generations": 10})
    f2 = fit(X, y, NAMES, backend="operon", units=UNITS, seed=3, options={"generations": 10})
    assert [c.expr for c in f1.candidates] == [c.expr for c in f2.candidates]


@pytest.mark.parametrize("backend", ["operon", "sindy"])
def test_fronts_of_several_targets_are_each_its_own_fit(backend):
    """fit_many gives, in order, the front fit() gives each target (operon: the searches side by
    side in threads), and leaves the process's warning filters as it found them."""
    import warnings

    calls = []
    for seed, law in enumerate([leakage, linear, leakage]):
        X, y = make_data(law, n=800, seed=seed)
        calls.append(dict(X=X, y=y, names=NAMES, backend=backend, units=UNITS, target=f"t{seed}", seed=seed,
                          options={"generations": 15} if backend == "operon" else {}))
    filters = list(warnings.filters)
    together = fit_many(calls)
    assert list(warnings.filters) == filters
    assert [f.target for f in together] == ["t0", "t1", "t2"]
    for call, front in zip(calls, together):
        alone = fit(**call)
        assert [(c.expr, c.complexity, c.mse) for c in front.candidates] == \
               [(c.expr, c.complexity, c.mse) for c in alone.candidates]
    with pytest.raises(SymbolicError, match="unknown"):  # a bad call is refused before any search
        fit_many([calls[0], {**calls[1], "options": {"no_such_option": 1}}])


@pytest.mark.parametrize(
    ("law", "term", "coefficient"),
    [(leakage, (A - B) * sympy.sqrt(sympy.Abs(A - B)), 1.3), (linear, A - B, 0.7)],
    ids=["leakage", "linear"],
)
def test_sindy_recovers_exactly_the_right_term(law, term, coefficient):
    X, y = make_data(law)
    front = fit(X, y, NAMES, backend="sindy", units=UNITS, target="zone1.air.T")
    i, _ = choose(front)
    chosen = front.candidates[i]
    assert list(chosen.terms) == [str(term)]
    assert chosen.complexity == 1
    assert chosen.terms[str(term)] == pytest.approx(coefficient, rel=0.01)
    assert sympy.simplify(chosen.expr / term).is_number
    assert fresh_r2(chosen.expr, law) >= 0.99


def test_sindy_library_is_generic_and_respects_units():
    names = ["a", "b", "c", "p", "q"]
    units = {"a": "K", "b": "K", "c": "degC", "p": "Pa", "q": "Pa"}
    X = np.random.default_rng(0).uniform(1.0, 2.0, (20, 5))
    labels = {t.label for t in library(X, names, units)}
    a, b, c, p, q = sympy.symbols(names)
    assert str(a - b) in labels and str(p - q) in labels
    assert str(a**4 - b**4) in labels  # kelvin pair: radiation term
    assert str(p**4 - q**4) not in labels
    assert str((p - q) * sympy.sqrt(sympy.Abs(p - q))) in labels and str((a - b) * sympy.Abs(a - b)) in labels
    # never a difference of different units (K vs degC, K vs Pa)
    for x, z in [(a, c), (a, p), (c, p), (b, q)]:
        assert str(x - z) not in labels and str(z - x) not in labels
    # a difference times each input of another unit
    assert str((a - b) * p) in labels and str((p - q) * a) in labels and str((a - b) * c) in labels
    assert str((a - b) * a) not in labels
    # inputs without a unit are never paired
    labels = {t.label for t in library(X, names, {})}
    assert labels == {"1", *names}


def _hand_front() -> ParetoFront:
    a, b = sympy.symbols("a b")
    cands = [
        Candidate(sympy.Float(2.0) * a, 3, 10.0, 0.5, "2*a"),
        Candidate(0.7 * (a - b), 7, 1.002, 0.95, "0.7*(a - b)"),
        Candidate(0.7 * (a - b) + 0.01 * a * b, 11, 1.0, 0.951, "..."),
    ]
    return ParetoFront("operon", "y", ["a", "b"], cands, n_points=1000)


def test_choose_rules_and_index_override():
    front = _hand_front()
    i, why = choose(front)
    assert i == 1 and why.startswith("Rule 'knee'") and "within 5%" in why
    assert choose(front, "knee", tol=0.0)[0] == 2
    assert choose(front, "best")[0] == 2
    i, why = choose(front, "bic")
    assert i == 1 and "n = 1000" in why
    i, why = choose(front, index=0)
    assert i == 0 and "index 0" in why and "knee" in why
    with pytest.raises(SymbolicError, match=r"^Pareto index must be in \[0, 2\], but got 9$"):
        choose(front, index=9)
    with pytest.raises(SymbolicError, match=r"Pareto index must be in \[0, 2\], but got -1"):
        choose(front, index=-1)
    with pytest.raises(SymbolicError, match="must be one of \\['score', 'knee', 'best', 'bic'\\], but got 'elbow'"):
        choose(front, "elbow")
    with pytest.raises(SymbolicError, match="empty Pareto front"):
        choose(ParetoFront("operon", "y", ["a"], []))


def test_index_message_for_eight_candidates():
    front = ParetoFront(
        "sindy", "y", ["a"], [Candidate(sympy.Symbol("a") * k, k, 10.0 - k, 0.1 * k, "") for k in range(1, 9)]
    )
    with pytest.raises(SymbolicError, match=r"Pareto index must be in \[0, 7\], but got 9"):
        choose(front, index=9)


def test_pareto_front_round_trips_through_json():
    X, y = make_data(leakage, n=400)
    front = fit(X, y, NAMES, backend="sindy", units=UNITS, target="zone1.air.T")
    text = json.dumps(front.to_dict())
    back = ParetoFront.from_dict(json.loads(text))
    assert [c.expr for c in back.candidates] == [c.expr for c in front.candidates]
    assert [(c.complexity, c.mse, c.r2, c.text, c.terms) for c in back.candidates] == [
        (c.complexity, c.mse, c.r2, c.text, c.terms) for c in front.candidates
    ]
    assert (back.backend, back.target, back.inputs, back.units, back.n_points) == (
        "sindy", "zone1.air.T", NAMES, UNITS, 400,
    )
    hand = _hand_front()
    assert [c.expr for c in ParetoFront.from_dict(json.loads(json.dumps(hand.to_dict()))).candidates] == [
        c.expr for c in hand.candidates
    ]
    with pytest.raises(SymbolicError, match="missing"):
        ParetoFront.from_dict({"backend": "operon"})


def test_pysr_without_julia_fails_fast_without_importing_pysr():
    if "pysr" in available_backends():
        pytest.skip("PySR and Julia are installed here")
    X, y = make_data(linear, n=50)
    start = time.perf_counter()
    with pytest.raises(BackendUnavailable) as err:
        fit(X, y, NAMES, backend="pysr")
    assert time.perf_counter() - start < 2.0
    assert str(err.value) == (
        "symbolic.backend=pysr needs PySR and a Julia installation (julia on PATH); none was found. "
        "Install Julia and `pip install physmend[pysr]`, or use symbolic.backend=operon"
    )
    assert isinstance(err.value, SymbolicError)
    assert "pysr" not in sys.modules and "juliacall" not in sys.modules


def test_importing_symbolic_is_light():
    code = (
        "import sys, physmend.symbolic, physmend.explain.mechanisms; "
        "print(sorted(m for m in ('pyoperon', 'pysindy', 'pysr', 'sklearn', 'torch') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"X": np.ones((20, 3)), "y": np.ones(19)}, "same number of points, but got X 20 and y 19"),
        ({"X": np.ones((20, 3)), "y": np.r_[np.ones(19), np.nan]}, "y must hold only finite values, but it has 1 non-finite"),
        ({"X": np.c_[np.ones((20, 2)), np.r_[np.inf, np.ones(19)]], "y": np.ones(20)}, "column 'fan.flow' has 1 non-finite values (first at row 0)"),
        ({"X": np.ones((20, 2)), "y": np.ones(20)}, "names must name every column of X (2), but got 3 names"),
        ({"X": np.ones((5, 3)), "y": np.ones(5)}, "at least 10 points, but got 5"),
        ({"X": np.ones((20, 3, 1)), "y": np.ones(20)}, "X must be 2-D with shape (n_points, n_inputs), but got shape (20, 3, 1)"),
    ],
    ids=["length", "y-nan", "x-inf", "names", "too-few", "x-3d"],
)
def test_bad_input_states_the_rule(kwargs, message):
    with pytest.raises(SymbolicError) as err:
        fit(kwargs["X"], kwargs["y"], NAMES, backend="sindy")
    assert message in str(err.value)


def test_unknown_backend_and_option_list_valid_names():
    X, y = make_data(linear, n=50)
    with pytest.raises(SymbolicError, match=r"must be one of \['operon', 'pysr', 'sindy'\], but got 'gplearn'"):
        fit(X, y, NAMES, backend="gplearn")
    with pytest.raises(SymbolicError, match=r"options of back end 'sindy' must be among \[.*'n_thresholds'.*\], but got unknown \['nthresholds'\]"):
        fit(X, y, NAMES, backend="sindy", options={"nthresholds": 3})
    with pytest.raises(SymbolicError, match="max_points must be an integer >= 10, but got 3"):
        fit(X, y, NAMES, backend="sindy", options={"max_points": 3})


def test_score_rule_picks_the_steepest_accuracy_gain() -> None:
    from physmend.symbolic import Candidate, ParetoFront, choose

    x = sympy.Symbol("x")
    mses = [1.0, 0.9, 0.01, 0.009, 0.0085]  # the big drop is at index 2
    front = ParetoFront(backend="test", target="y", inputs=["x"],
                        candidates=[Candidate(expr=x * k, complexity=3 + 2 * k, mse=m, r2=1 - m, text=str(x * k)) for k, m in enumerate(mses)])
    idx, why = choose(front, "score")
    assert idx == 2 and "Rule 'score'" in why


def test_prepare_imports_the_back_end_s_library_ahead_and_never_pysr_s() -> None:
    """``prepare``: in a fresh process pyoperon's regressor is not imported until ``prepare('operon')``
    imports it; ``prepare('pysr')`` imports nothing (importing PySR may start Julia's set-up); an
    unknown back end is an error naming the choices."""
    code = ("import sys; from physmend.symbolic import prepare; a = 'pyoperon.sklearn' in sys.modules;"
            "prepare('operon'); prepare('pysr');"
            "print(a, 'pyoperon.sklearn' in sys.modules, 'pysr' in sys.modules, 'juliacall' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.split() == ["False", "True", "False", "False"]
    with pytest.raises(SymbolicError, match="symbolic.backend must be one of"):
        prepare("eureqa")
