"""Products and ratios of two variables as candidate formulas, from the data rather than the network.

On a short record the network is shaped by few samples: a product of two states (a reaction or
encounter rate, mass action) may be missing from the regression's front although the recordings
would pick it. Products ``c·a·b``, ratios ``c·a/b`` and squares ``c·a²`` of the candidate inputs
(states, inputs, recorded quantities; not parameters) are formed with one constant each, the
:data:`MAX_LIBRARY` that fit the target best are offered, and the choice by simulation through the
model decides among them and the front (:func:`physmend.symbolic.choice.choose_by_simulation`).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp

#: at most this many library terms (those fitting the target best) join a front
MAX_LIBRARY = 12


def pair_candidates(names: Sequence[str], columns: Mapping[str, np.ndarray], y: np.ndarray, *,
                    operators: Mapping[str, int] | None = None, limit: int = MAX_LIBRARY,
                    units: Mapping[str, str] | None = None) -> list[Any]:
    """``c·a·b``, ``c·a/b`` (``b`` never zero on the samples) and ``c·a²`` over ``names``.

    Args:
        names: variable names, each a key of ``columns`` (values ``(N,)`` along the training samples).
        y: the target ``(N,)`` in the equation's units; each term's one constant is fitted to it.
        operators: complexity prices (:func:`physmend.symbolic.operators.priced_size`); None: tree size.
        limit: the terms kept, by their fit of ``y`` (the network's correction: on a short record a
            rough ranking, so the caller simulates several).
        units: declared units by name: a product, ratio or square of quantities on a scale with an
            offset (°C) is never offered (:func:`physmend.modeling.interval.interval_violation`).

    Returns:
        Candidates marked ``[library: …]``, best fit first.
    """
    from physmend.symbolic import Candidate, display, mse_r2
    from physmend.symbolic.choice import nearly_constant, tree_size
    from physmend.symbolic.operators import priced_size

    usable = [n for n in names if n in columns and np.isfinite(columns[n]).all() and not nearly_constant(columns[n])]
    shapes: list[tuple[sp.Expr, np.ndarray, str]] = []
    for a, b in itertools.combinations(usable, 2):
        va, vb = np.asarray(columns[a], float), np.asarray(columns[b], float)
        shapes.append((sp.Symbol(a) * sp.Symbol(b), va * vb, "product"))
        for num, den, vn, vd in ((a, b, va, vb), (b, a, vb, va)):
            if np.all(vd != 0):
                shapes.append((sp.Symbol(num) / sp.Symbol(den), vn / vd, "ratio"))
    for a in usable:
        va = np.asarray(columns[a], float)
        shapes.append((sp.Symbol(a) ** 2, va * va, "square"))
    from physmend.modeling.interval import interval_violation

    out = []
    for shape, t, kind in shapes:
        if units and interval_violation(shape, dict(units)) is not None:
            continue
        tt = float(t @ t)
        if not np.isfinite(tt) or tt == 0.0:
            continue
        c = float(t @ y) / tt
        mse, r2 = mse_r2(y, c * t)
        expr = sp.Float(c) * shape
        size = tree_size(expr) if operators is None else priced_size(expr, operators)
        out.append(Candidate(expr=expr, complexity=int(size), mse=mse, r2=r2,
                             text=f"{display(expr)}   [library: {kind}]"))
    out.sort(key=lambda c: -c.r2)
    return out[:limit]
