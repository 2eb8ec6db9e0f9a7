"""A chosen Pareto candidate as a :class:`~physmend.modeling.Correction`: the catalogue's clean form
where it reproduces the candidate, numeric constants named (``c1``, ``c2`` …), labelled in its
equation's units."""

from __future__ import annotations

from typing import Any

import numpy as np
import sympy as sp

from physmend.symbolic.constants import identifiable, name_constants
from physmend.symbolic.targets import equation_unit


def canonical_form(expr: sp.Expr, columns: dict[str, np.ndarray], units: dict[str, str], min_r2: float) -> tuple[sp.Expr, str, float] | None:
    """The mechanism catalogue's clean form of ``expr`` (one constant) if it reproduces ``expr``
    on the samples (``columns``: ``(N,)`` each) with R² ≥ ``min_r2``; ``None`` otherwise."""
    from physmend.explain.catalogue import load_catalogue
    from physmend.explain.mechanisms import classify

    used = {s.name for s in expr.free_symbols}
    if not used or not used <= set(columns):
        return None
    matches = classify(expr, {n: columns[n] for n in used}, units, top=1)
    if not matches or matches[0].r2 < min_r2:
        return None
    m = matches[0]
    entry = next(e for e in load_catalogue() if e.id == m.id)
    mapping = {sp.Symbol(ph): sp.Symbol(var) for ph, var in m.variables.items()}
    for s in entry.template.free_symbols:
        if s.name in m.variables:
            mapping[s] = sp.Symbol(m.variables[s.name])
    constants = {"c": m.coefficient, **({"k": m.k} if entry.k and m.k is not None else {})}
    clean = entry.template.xreplace({**mapping, **{s: sp.Float(constants[s.name]) for s in entry.template.free_symbols
                                                   if s.name in constants}})
    return clean, m.name, m.r2


def correction_for(problem: Any, state: str, front: Any, idx: int, why: str, columns: dict[str, np.ndarray],
                   units: dict[str, str], sc: Any, chosen: dict[str, Any]) -> Any:
    """The correction for Pareto candidate ``idx`` of ``front`` (clean catalogue form when it fits
    with R² ≥ ``sc.canonical_r2``); records the choice (index, ``why``, expressions, unit) in
    ``chosen[state]``."""
    from physmend.modeling import Correction

    unit = equation_unit(problem.model, state, getattr(problem, "time_unit", "s"))
    raw = front.candidates[idx].expr
    canonical = canonical_form(raw, columns, units, float(sc.canonical_r2))
    if canonical is not None:
        why += (f" Its form matches the catalogue's {canonical[1]!r} with R² {canonical[2]:.4f} ≥ "
                f"{float(sc.canonical_r2)} on the training samples, so that clean form is used.")
    expr, consts = name_constants(canonical[0] if canonical is not None else identifiable(raw))
    chosen[state] = {"index": idx, "why": why, "expr": str(raw), "unit": unit,
                     "canonical": str(canonical[0]) if canonical is not None else None}
    return Correction(state=state, term=sp.sstr(expr), constants=consts, unit=unit)
