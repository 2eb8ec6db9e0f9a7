"""Formulas scaled by a parameter that differs between the training experiments.

A missing term often scales with a parameter of the configuration (an area, a length, a mass) that
the training experiments set to only two values. The network does not see such a parameter (it
could memorise the experiments with it: :data:`physmend.ude.spec.MIN_PARAMETER_VALUES`), so its
corrections carry the average size; the formulas fitted to them carry no parameter. Each such
formula ``f`` is therefore offered again as ``α·p·f`` and ``α·f/p`` for every parameter ``p`` of
:func:`physmend.ude.spec.scale_parameters`: one shared scale ``α`` (re-fitted to the target), the
ratio between the experiments fixed by ``p``. Which one (if any) holds is decided by the data — the
recorded mismatch of every training experiment or the corrected model's simulation — by the same
rule as every other candidate.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp

#: at most this many of a front's candidates (those fitting the target best) are scaled
MAX_SCALED = 6


def scaled_variants(candidates: Sequence[Any], parameters: Sequence[str], columns: Mapping[str, np.ndarray],
                    y: np.ndarray, *, operators: Mapping[str, int] | None = None,
                    limit: int = MAX_SCALED, units: Mapping[str, str] | None = None) -> list[Any]:
    """``α·p·f`` and ``α·f/p`` for the ``limit`` candidates that fit ``y`` best and each parameter.

    Args:
        candidates: a front's :class:`physmend.symbolic.Candidate` objects.
        parameters: parameter names, each a key of ``columns``.
        columns: name -> values ``(N,)`` along the training samples (every symbol of the candidates
            and every parameter).
        y: the target ``(N,)`` (the network's correction, in the equation's units).
        operators: complexity prices (:func:`physmend.symbolic.operators.priced_size`); None: tree size.
        limit: how many candidates are scaled.
        units: declared units by name: a variant that uses a quantity on a scale with an offset (°C)
            other than as a difference is left out (:func:`physmend.modeling.interval.interval_violation`).

    Returns:
        New candidates (scale re-fitted by least squares on ``y``), each marked ``[scaled by p]``.
    """
    from physmend.modeling.interval import interval_violation
    from physmend.symbolic import Candidate, display, evaluate, mse_r2
    from physmend.symbolic.choice import tree_size
    from physmend.symbolic.operators import priced_size

    if not parameters or not candidates:
        return []
    best = sorted(candidates, key=lambda c: -c.r2)[:limit]
    out: list[Any] = []
    for c in best:
        base = c.expr
        if not isinstance(base, sp.Basic) or base == 0:
            continue
        for p in parameters:
            if p not in columns:
                continue
            sym = sp.Symbol(p)
            values = np.asarray(columns[p], dtype=float)
            terms = sp.Add.make_args(base)
            shapes = [(1, base * sym)]
            if np.all(values != 0):
                shapes.append((-1, base / sym))
            for power, shape in shapes:
                if units and interval_violation(shape, dict(units)) is not None:
                    continue
                t = evaluate(shape, columns, n=y.size)
                if not np.isfinite(t).all():
                    continue
                tt = float(t @ t)
                if tt == 0.0:
                    continue
                alpha = float(t @ y) / tt
                # the scale folded into each term's own constant: α·p·(c1·u + c2) has two constants, not three
                expr = sp.Add(*[sp.Float(alpha) * a * sym**power for a in terms])
                mse, r2 = mse_r2(y, alpha * t)
                size = tree_size(expr) if operators is None else priced_size(expr, operators)
                out.append(Candidate(expr=expr, complexity=int(size), mse=mse, r2=r2,
                                     text=f"{display(expr)}   [scaled by {p}]"))
    return out
