"""Formulas scaled by a two-valued parameter, products of two variables from the data, and the rule
that a form of two-valued parameters alone never gets an offset (it would memorise the experiments)."""

from __future__ import annotations

import numpy as np
import sympy as sp

from physmend.modeling.evaluate import n_constants
from physmend.symbolic import Candidate
from physmend.symbolic.choice import catalogue_candidates
from physmend.symbolic.library import pair_candidates
from physmend.symbolic.scaled import scaled_variants


def _two_experiments(n: int = 300) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(3)
    return {"heater.u": rng.uniform(0.5, 2.0, 2 * n), "pipe.L": np.repeat([2.0, 4.0], n)}


def test_a_scaled_variant_fits_a_term_that_grows_with_the_parameter_with_the_constants_it_had() -> None:
    cols = _two_experiments()
    y = -0.7 * cols["pipe.L"] * cols["heater.u"]
    u = sp.Symbol("heater.u")
    front = [Candidate(expr=sp.Float(-2.1) * u + sp.Float(0.05), complexity=5, mse=1.0, r2=0.7, text="network's")]
    out = scaled_variants(front, ["pipe.L"], cols, y)
    by_text = {c.text.split("   ")[0]: c for c in out}
    best = max(out, key=lambda c: c.r2)
    assert "pipe.L" in best.text and "/pipe.L" not in best.text and best.r2 > 0.99, by_text
    assert all(n_constants(c.expr) == 2 for c in out)  # the scale folded into the form's own constants
    assert all("[scaled by pipe.L]" in c.text for c in out)


def test_a_parameter_that_only_labels_the_experiments_gets_no_offset_from_the_catalogue() -> None:
    cols = _two_experiments()
    offsets = np.where(cols["pipe.L"] == 2.0, -3.0, 5.0)  # two per-experiment offsets: anything fits them with 2 constants
    y = offsets + 0.1 * cols["heater.u"]
    cands = catalogue_candidates(["heater.u", "pipe.L"], {"heater.u": "W", "pipe.L": "m"}, cols, y,
                                 scale_only={"pipe.L"})
    alone = [c for c in cands if c.expr.free_symbols == {sp.Symbol("pipe.L")}]
    assert alone and all(n_constants(c.expr) == 1 for c in alone), [c.text for c in alone]
    assert max(c.r2 for c in alone) < 0.9  # one constant times the length cannot reproduce the two offsets
    free = catalogue_candidates(["heater.u", "pipe.L"], {"heater.u": "W", "pipe.L": "m"}, cols, y)
    assert max(c.r2 for c in free if c.expr.free_symbols == {sp.Symbol("pipe.L")}) > 0.999  # without the rule it would


def test_products_and_ratios_of_two_variables_are_offered_with_one_constant() -> None:
    rng = np.random.default_rng(0)
    cols = {"s.x": rng.uniform(0.5, 3.0, 200), "s.y": rng.uniform(0.2, 1.5, 200), "feed.u": rng.uniform(0, 1, 200)}
    y = -0.4 * cols["s.x"] * cols["s.y"]
    out = pair_candidates(list(cols), cols, y)
    assert out[0].expr.free_symbols == {sp.Symbol("s.x"), sp.Symbol("s.y")} and out[0].r2 > 0.999
    assert "[library: product]" in out[0].text and all(n_constants(c.expr) == 1 for c in out)
    y2 = 2.0 * cols["s.x"] / cols["s.y"]
    assert "[library: ratio]" in pair_candidates(list(cols), cols, y2)[0].text
