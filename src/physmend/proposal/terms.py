"""The proposed terms along the corrected model's training trajectories: their size in physical
units and the mechanisms of the catalogue their forms match."""

from __future__ import annotations

from typing import Any

import numpy as np
import sympy as sp
import torch


def training_samples(model: Any, experiments: list[Any], batch: Any, traj: Any) -> dict[str, np.ndarray]:
    """Every state, input, observed variable and parameter of ``model`` along the trajectories
    ``traj`` (on the grid of ``batch``) of the training experiments, each flattened to ``(T·n,)``."""
    train_b = [b for b, e in enumerate(experiments) if e.role == "train"]
    samples: dict[str, np.ndarray] = {}
    names_all = model.state_names + model.input_names
    values_all = torch.cat([traj.states, traj.inputs], -1)
    for i, n in enumerate(names_all):
        samples[n] = values_all[:, train_b, i].reshape(-1).numpy()
    for i, n in enumerate(model.observed):
        samples[n] = traj.observed[:, train_b, i].reshape(-1).numpy()
    for i, n in enumerate(model.parameter_names):
        samples[n] = np.repeat(batch.params[train_b, i].numpy()[None], batch.t.shape[0], 0).reshape(-1)
    return samples


def describe_terms(corrections: list[Any], written: Any, corrected: Any, samples: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Per correction: the term (text and ``sympy``, parsed by the restricted parser), its constants,
    unit, the equation it corrects (``written``: the model as written) and its component, its mean
    and largest size along ``samples`` (:func:`training_samples` of the ``corrected`` model) and the
    catalogue's mechanisms ranked by how well their forms reproduce it there."""
    from physmend.explain.mechanisms import classify
    from physmend.modeling.compile import lambdify_torch
    from physmend.modeling.expressions import parse_expression

    sm = corrected
    terms = []
    symbols = {v.name: v.symbol for v in sm.states + sm.inputs + sm.parameters}
    symbols.update({n: sp.Symbol(n) for n in sm.observed if n not in symbols})  # a formula may use a recorded quantity
    for c in corrections:
        consts = {k: v for k, v in c.constants.items()}
        expr = parse_expression(c.term, {**symbols, **{k: sp.Symbol(k) for k in consts}}, where=c.state)
        expr_num = expr.subs(consts)
        fn = lambdify_torch(list(symbols.values()), [expr_num], "correction")
        vals = fn(*[torch.as_tensor(samples[n]) for n in symbols])[0]
        vals = torch.as_tensor(vals).expand(len(next(iter(samples.values())))).numpy()
        units = {n: sm.units.get(n, "") for n in samples}
        matches = classify(expr_num, {n: samples[n] for n in samples if n in {s.name for s in expr_num.free_symbols}}, units)
        terms.append({"state": c.state, "term": c.term, "sympy": expr, "constants": consts, "unit": c.unit, "expr": str(expr_num),
                      "equation": written.equation_text.get(c.state, ""), "owner": sm.owner.get(c.state, ""),
                      "mean_abs": float(np.mean(np.abs(vals))), "max_abs": float(np.max(np.abs(vals))),
                      "mechanisms": [m.__dict__ for m in matches]})
    return terms
