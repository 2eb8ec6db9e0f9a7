"""What the regression fits: the inputs (columns along the training samples) and, per kept
equation, the target — the network's correction in the units of that equation's terms (``a·ΔNN``
for an equation ``a·der(x) = …``: watts for a heat balance), so a formula need not know capacities
and generalises across configurations."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


def equation_unit(model: Any, state: str, time_unit: str = "s") -> str:
    """The unit of the terms of ``state``'s equation: for ``der(x) = …`` (coefficient 1) the rate
    ``unit(x)/time_unit``; otherwise the unit of a variable of its right-hand side whose dimension is
    the right-hand side's (a heat flow in a heat balance ``C·der(T) = P − UA·(T − T_room)``, not a
    temperature), the first such by name; the first variable's unit when the units cannot tell."""
    if model.der_coefficient.get(state, 1) == 1 and model.units.get(state):
        return f"{model.units[state]}/{time_unit}"
    eq = model.equations.get(state)
    if eq is None:
        return ""
    from physmend.modeling.units import ANY, UnitMismatch, dimension, formula_dimension, same

    labels = [model.units.get(sym.name, "") for sym in sorted(eq.rhs.free_symbols, key=lambda s: s.name)
              if sym.name not in model.parameter_names]
    labels = [u for u in labels if u]
    try:  # the right-hand side's dimension, from every declared unit (parameters' included)
        want = formula_dimension(eq.rhs, model.units)
    except UnitMismatch:
        want = ANY
    if want is not ANY:
        for unit in labels:
            d = dimension(unit)
            if d is not None and same(d, want):  # type: ignore[arg-type]
                return unit
    return labels[0] if labels else ""


def measured_quantities(problem: Any, traj: Any, kept: list[str], have: set[str]) -> dict[str, np.ndarray]:
    """The recorded quantities that measure a kept state through a factor of the parameters (a
    concentration ``A/V`` of an amount ``A``: :mod:`physmend.ude.measured`), as formula inputs
    ``(N,)`` along the training samples: a missing term often acts on the measured quantity, not
    on the state it is stored in (an elimination on the concentration). Only outputs that are model
    variables (a formula names them); those already in ``have`` are left out."""
    from physmend.ude.measured import recorded_quantities

    wanted = [n for n in recorded_quantities(problem.model, problem.compiled.observed_names, kept) if n not in have]
    if not wanted:
        return {}
    with torch.no_grad():
        values = problem.compiled.observed(traj.u, traj.x, traj.p)
    order = problem.compiled.observed_names
    return {n: values[:, order.index(n)].numpy() for n in wanted}


def targets(hybrid: Any, problem: Any, traj: Any, kept: list[str]) -> dict[str, np.ndarray]:
    """``a·correction`` per kept state along the training samples: ``(N,)`` each, equation units."""
    from physmend.ude.analysis import equation_corrections

    values = equation_corrections(hybrid, problem, traj, kept)
    return {name: values[:, i].numpy() for i, name in enumerate(kept)}


@dataclass
class RegressionData:
    """The regression's data along the ``N`` training samples.

    ``columns``: every named quantity ``(N,)`` — the regression's variables ``x_names`` and the
    scale parameters (a scale of a form, never a variable); ``X``: ``(N, len(x_names))``;
    ``units``: the unit of each variable and scale parameter; ``y``: the target ``(N,)`` per kept
    state, in its equation's units."""

    columns: dict[str, np.ndarray]
    x_names: list[str]
    X: np.ndarray
    units: dict[str, str]
    y: dict[str, np.ndarray]


def regression_data(hybrid: Any, problem: Any, traj: Any, kept: list[str], inputs: list[str],
                    parameters: list[str], scale: list[str]) -> RegressionData:
    """The network's (normalised) ``inputs`` and the model's ``parameters`` along the training
    trajectories ``traj``, joined by the recorded quantities that measure a kept state
    (:func:`measured_quantities`); the ``scale`` parameters as columns but not variables; the
    targets of :func:`targets`."""
    names = hybrid.spec.input_names
    with torch.no_grad():
        feats = hybrid.features(traj.u, traj.x, traj.p).numpy()
    columns = {n: feats[:, names.index(n)] for n in inputs if n in names}
    for p in parameters:
        columns[p] = traj.p[:, problem.model.parameter_names.index(p)].numpy()
    columns.update(measured_quantities(problem, traj, kept, set(columns)))
    x_names = list(columns)
    X = np.stack([columns[n] for n in x_names], axis=1)
    for p in scale:  # after X: not a variable of the regression
        columns[p] = traj.p[:, problem.model.parameter_names.index(p)].numpy()
    units = {n: problem.model.units.get(n, "") for n in [*x_names, *scale]}
    return RegressionData(columns, x_names, X, units, targets(hybrid, problem, traj, kept))
