"""The hybrid's specification from ``cfg.ude``: corrected equations (definitions left out), network
inputs (parameters under ``auto``), normalisation, jointly estimated parameters. Imports ``hybrid``,
``reference``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from physmend.problem import Problem
from physmend.ude.hybrid import HybridSpec, UDEConfigError, der_coefficients, match_names
from physmend.ude.reference import Reference, _stats, train_mask


MIN_PARAMETER_VALUES = 3
"""A parameter is a *network* input under ``auto`` when it takes at least this many distinct values
across the training experiments. The number is not a tuning: two points are always joined by a line
exactly, so a dependence on a parameter seen at two values cannot be tested by the data — a network
given it could shape one function per value and memorise each experiment. A third value tests the
shape. A formula may still use a parameter seen at two values, but only through one shared constant
(:func:`scale_parameters`)."""


def informative_parameters(problem: Problem, min_values: int = MIN_PARAMETER_VALUES) -> list[str]:
    """Parameters that take at least ``min_values`` distinct values across the training experiments."""
    train = [e for e in problem.experiments if e.role == "train"]
    if len(train) < min_values:
        return []
    values = np.stack([np.asarray(e.parameters, dtype=float) for e in train])  # (E, n_params)
    out = []
    for j, name in enumerate(problem.model.parameter_names):
        col = values[:, j]
        tol = 1e-9 * max(float(np.abs(col).max()), 1.0)
        distinct = np.unique(np.round(col / tol)) if tol > 0 else np.unique(col)
        if distinct.size >= min_values:
            out.append(name)
    return out


def scale_parameters(problem: Problem) -> list[str]:
    """Parameters that differ between the training experiments (two values are enough) but are not
    network inputs (:func:`informative_parameters`): the formula search uses each as a *scale* of a
    form of the states and inputs — one constant times the parameter times the form (``c·p·u``) or
    divided by it — and in the catalogue's one-constant forms (never with a second fitted constant or
    an offset: :func:`physmend.symbolic.choice.catalogue_candidates`). Such a formula cannot memorise the experiments: its constant is shared, so the
    ratio between two experiments' terms is fixed by the parameter, and the recordings of both test
    it. A free regression variable could (``c1 + c2·p`` fits any two per-experiment offsets), so the
    parameter is never one (:mod:`physmend.symbolic.scaled`)."""
    network = set(informative_parameters(problem))
    return [p for p in informative_parameters(problem, 2) if p not in network]


def identity_states(problem: Problem) -> list[str]:
    """States whose equation is a definition, ``der(x) = y`` with ``y`` another state (a position and
    its velocity): nothing physical can be missing from it, so a correction there could only be a
    solver artefact standing in for physics missing elsewhere (the seed paper's dummy derivatives)."""
    model = problem.model
    states = set(model.state_names)
    out = []
    for name in model.state_names:
        rhs, coef = model.rhs.get(name), model.der_coefficient.get(name, 1)
        if rhs is not None and getattr(rhs, "is_Symbol", False) and rhs.name in states and rhs.name != name \
                and coef == 1:
            out.append(name)
    return out


def recorded_quantities(problem: Problem) -> list[str]:
    """Algebraic variables that are recorded outputs measuring a state through a factor of the
    parameters (a concentration ``A/V`` of an amount: :mod:`physmend.ude.measured`): what
    ``ude.inputs.observed: auto`` gives the network — a missing term often acts on the measured
    quantity, and only the quantity carries over to experiments whose factor training never saw."""
    from physmend.ude.measured import recorded_quantities as recorded

    return recorded(problem.model, problem.compiled.observed_names)


def build_spec(cfg: Any, problem: Problem, ref: Reference) -> HybridSpec:
    """Choose corrected equations and network inputs from ``cfg.ude``; normalise from ``ref``.

    ``ude.corrected`` patterns select the corrected equations; a pattern that is a wildcard (``*``)
    leaves out definitional equations (:func:`identity_states`); naming one corrects it."""
    from physmend.settings import training_settings

    cfg = training_settings(cfg)
    ude = cfg.ude
    model = problem.model
    corrected = match_names(list(ude.corrected), model.state_names, "ude.corrected")
    named = {str(p) for p in ude.corrected}
    corrected = [n for n in corrected if n in named or n not in identity_states(problem)]
    sel = ude.inputs
    in_states = _selected(sel.states, model.state_names, "ude.inputs.states")
    if isinstance(sel.observed, str):
        if sel.observed != "auto":
            raise UDEConfigError(f"ude.inputs.observed must be 'auto' or a list of names/patterns, but got {sel.observed!r}")
        in_observed = recorded_quantities(problem)
    else:
        in_observed = match_names(list(sel.observed or []), list(model.observed), "ude.inputs.observed")
    in_inputs = _selected(sel.inputs, model.input_names, "ude.inputs.inputs")
    if isinstance(sel.parameters, str):
        if sel.parameters != "auto":
            raise UDEConfigError(f"ude.inputs.parameters must be 'auto' or a list of names/patterns, but got {sel.parameters!r}")
        in_params = informative_parameters(problem)
    else:
        in_params = match_names(list(sel.parameters or []), model.parameter_names, "ude.inputs.parameters")
    if not (in_states or in_observed or in_inputs or in_params):
        raise UDEConfigError("ude.inputs selects no network input; enable states, inputs, observed or parameters")
    estimated = [v.name for v in model.parameters if v.uncertain] if cfg.train.estimate_parameters else []
    widths = [int(ude.width)] * int(ude.depth)
    mask = train_mask(problem, ref.batch)
    cm = problem.compiled
    feats = [ref.states[..., [cm.state_names.index(n) for n in in_states]]]
    if in_observed:
        feats.append(ref.observed[..., [cm.observed_names.index(n) for n in in_observed]])
    if in_inputs:
        feats.append(ref.inputs[..., [cm.input_names.index(n) for n in in_inputs]])
    if in_params:
        p = ref.batch.params[:, [cm.parameter_names.index(n) for n in in_params]]
        feats.append(p[None].expand(ref.states.shape[0], -1, -1))
    mean, std = _stats(torch.cat(feats, -1), mask)
    units = ude.units
    idx = [cm.state_names.index(n) for n in corrected]
    d = ref.derivs[..., idx][mask]
    rms = _rms(d)
    rate_rms = rms
    if units == "equation" and corrected:
        # the same size in the equation's own units: a_i·du_i/dt (W for a heat balance, N for a force)
        coef = der_coefficients(problem, corrected)(ref.batch.params)  # (B, k), the parameters as given
        rms = _rms((ref.derivs[..., idx] * coef[None])[mask])
    return HybridSpec(
        corrected=corrected,
        in_states=in_states,
        in_observed=in_observed,
        in_inputs=in_inputs,
        in_parameters=in_params,
        widths=widths,
        activation=str(ude.activation),
        mean=mean.tolist(),
        std=std.tolist(),
        out_scale=(float(ude.output_scale) * rms).tolist(),
        units=units,
        rate_scale=(float(ude.output_scale) * rate_rms).tolist(),
        estimated=estimated,
        **state_range(ref.states, mask),
    )


def _selected(value: Any, names: list[str], key: str) -> list[str]:
    """``true``: every name; ``false``: none; a list: the names its glob patterns match."""
    if isinstance(value, bool):
        return list(names) if value else []
    if isinstance(value, str):
        raise UDEConfigError(f"{key} must be true, false or a list of names/patterns, but got {value!r}")
    return match_names(list(value), names, key)


def _rms(d: torch.Tensor) -> torch.Tensor:
    """RMS of each column of ``d (N, k)``; a column that is all zero gets the largest RMS (or 1e-9)."""
    rms = d.pow(2).mean(0).sqrt()
    if rms.numel():
        rms = torch.where(rms > 0, rms, torch.ones_like(rms) * rms.max().clamp_min(1e-9))
    return rms


#: a state's range is at least this share of its magnitude (a nearly constant temperature in kelvin
#: gets a range of tens of kelvin, not the millikelvin it happened to move in training)
MIN_RELATIVE_RANGE = 0.1


def state_range(states: torch.Tensor, mask: torch.Tensor) -> dict[str, list[float | None]]:
    """Each state's range over the training samples ``mask (T, B)`` of ``states (T, B, n)`` (the model
    as written), at least :data:`MIN_RELATIVE_RANGE` of its magnitude; None for a state held at zero."""
    values = states[mask]
    values = values[torch.isfinite(values).all(-1)]
    low: list[float | None] = []
    high: list[float | None] = []
    for j in range(states.shape[-1]):
        if values.shape[0] == 0:
            low.append(None), high.append(None)
            continue
        a, b = float(values[:, j].min()), float(values[:, j].max())
        pad = max(0.0, MIN_RELATIVE_RANGE * max(abs(a), abs(b)) - (b - a)) / 2
        if b - a + 2 * pad <= 0.0:
            low.append(None), high.append(None)
        else:
            low.append(a - pad), high.append(b + pad)
    return {"state_low": low, "state_high": high}
