"""Which states the recordings measure: an output that is a state, or a state times a factor of the
parameters only — a concentration ``A/V`` of an amount, a level ``V/area`` of a volume, a
temperature ``E/C`` of an energy. The record of such an output, divided by its factor (per
experiment: a volume may differ between them), is a record of the state itself.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from typing import Any

import sympy as sp
import torch


def measured_outputs(model: Any) -> list[tuple[int, int, sp.Expr]]:
    """``(output index, state index, factor)`` for every output ``y = factor(p)·x`` of one state
    ``x`` (``factor`` 1 for the state itself); other outputs measure no single state."""
    names = model.state_names
    params = set(model.parameter_names)
    out = []
    for j, name in enumerate(model.output_names):
        expr = sp.sympify(model.outputs[name])
        if getattr(expr, "is_Symbol", False) and expr.name in names:
            out.append((j, names.index(expr.name), sp.Integer(1)))
            continue
        states = [s for s in expr.free_symbols if s.name in names]
        if len(states) != 1 or any(s.name not in params for s in expr.free_symbols - set(states)):
            continue
        x = states[0]
        factor = sp.diff(expr, x)
        if x in factor.free_symbols or factor == 0 or sp.simplify(expr - factor * x) != 0:
            continue  # not proportional to the state (a nonlinear output, an offset)
        out.append((j, names.index(x.name), factor))
    return out


def factors(model: Any) -> Callable[[torch.Tensor], torch.Tensor]:
    """``g(p) -> (B, q)``: each measured output's factor (:func:`measured_outputs` order) for
    parameters ``p (B, n_params)``."""
    from physmend.modeling.compile import lambdify_torch

    exprs = [f for _, _, f in measured_outputs(model)]
    fn = lambdify_torch([v.symbol for v in model.parameters], exprs or [sp.Integer(1)], "output factors")

    def g(p: torch.Tensor) -> torch.Tensor:
        if not exprs:
            return p.new_ones(p.shape[:-1] + (0,))
        vals = fn(*p.unbind(-1))
        return torch.stack([torch.as_tensor(v, dtype=p.dtype, device=p.device).expand(p.shape[:-1]) for v in vals], -1)

    return g


def recorded_quantities(model: Any, observed: Collection[str], states: Collection[str] | None = None) -> list[str]:
    """Algebraic variables (names in ``observed``) that are recorded outputs measuring a state
    through a factor other than 1 (a concentration ``A/V``); only those of ``states`` if given."""
    names = [model.output_names[j] for j, i, f in measured_outputs(model)
             if f != 1 and (states is None or model.state_names[i] in states)]
    return [n for n in names if n in set(observed)]
