"""Counting and naming a formula's constants: a value repeated up to its sign is one constant."""

from __future__ import annotations

import sympy as sp

from physmend.modeling.evaluate import n_constants
from physmend.symbolic.constants import name_constants


def test_an_expanded_common_factor_is_one_constant() -> None:
    """sympy expands ``c·(T⁴ − R⁴)`` into ``c·T⁴ − c·R⁴``: still one constant, named once and
    written back as the factor (a BIC that counted two chose a worse one-constant form)."""
    T, R = sp.symbols("T R")
    radiation = -4.5e-9 * (T**4 - R**4)
    assert radiation.atoms(sp.Float) == {sp.Float(-4.5e-9), sp.Float(4.5e-9)}  # sympy did expand it
    assert n_constants(radiation) == 1
    named, consts = name_constants(radiation)
    assert consts == {"c1": -4.5e-9}
    c1 = sp.Symbol("c1")
    assert sp.simplify(named - c1 * (T**4 - R**4)) == 0
    assert sp.simplify(named.subs(c1, consts["c1"]) - radiation) == 0


def test_distinct_constants_stay_distinct() -> None:
    T, R = sp.symbols("T R")
    expr = 2.5 * T - 1.3 * R + 0.1
    assert n_constants(expr) == 3
    named, consts = name_constants(expr)
    assert sorted(consts.values()) == [-1.3, 0.1, 2.5]
    assert sp.simplify(named.subs({sp.Symbol(k): v for k, v in consts.items()}) - expr) == 0
    assert n_constants(sp.Integer(0) + T) == 1  # at least one (the scale)


def test_a_formula_whose_constants_trade_off_is_multiplied_out() -> None:
    """``c1·i·w·(c3·i + c4) + c2`` (a regression's shape) has three constants the data can pin down,
    not four: it is proposed as ``a·i²·w + b·i·w + c``; a form that multiplying out would not simplify,
    or would grow past half its size again, stays as found."""
    import sympy as sp

    from physmend.symbolic.constants import identifiable, name_constants

    i, w, T, Tr = sp.symbols("field.i shaft.w T Tr")
    found = -33.91 * i * w * (0.002406 * i + 0.00126) - 0.2486
    expr, consts = name_constants(identifiable(found))
    assert len(consts) == 3 and sp.expand(expr.subs(consts) - found) == 0
    radiation = -5.1e-8 * T**4 + 5.1e-8 * Tr**4
    assert identifiable(radiation) == radiation
    grows = 0.3 * (i + 2.0 * w) ** 6
    assert identifiable(grows) == grows
