"""Experiments stacked into one batch for a single batched solve."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from physmend.modeling.compile import BoundRhs, CompiledModel
from physmend.simulate.core import CLOCK_METHODS, OWN_METHODS, odeint
from physmend.simulate.inputs import PiecewiseLinear, from_channels


@dataclass
class Batch:
    """Experiments on one shared time axis.

    Attributes:
        ids: experiment ids, one per batch element ``B``.
        t: ``(T,)`` union of the experiments' observation times, seconds from each start.
        obs: ``(T, B, n_outputs)`` measurements, NaN where not measured (or past an experiment's end).
        inputs: batched piecewise-linear exogenous inputs.
        params: ``(B, n_params)`` parameter values.
        u0: ``(B, n_states)`` initial states.
        split_time: ``(B,)`` time from which samples are validation (inf: none).
        initial_ranges: per batch element, state name -> ``(low, high)`` of an initial value declared
            unknown (its entry of ``u0`` is mid-range until :mod:`physmend.simulate.initial` estimates it).
    """

    ids: list[str]
    t: torch.Tensor
    obs: torch.Tensor
    inputs: PiecewiseLinear
    params: torch.Tensor
    u0: torch.Tensor
    split_time: torch.Tensor
    initial_ranges: list[dict[str, tuple[float, float]]] = field(default_factory=list)

    @property
    def size(self) -> int:
        return len(self.ids)

    def take(self, rows: Sequence[int] | torch.Tensor, ids: list[str] | None = None) -> "Batch":
        """The batch elements ``rows`` (a subset or a repetition), on the same time axis."""
        idx = torch.as_tensor(rows, dtype=torch.long)
        ranges = [self.initial_ranges[i] for i in idx.tolist()] if self.initial_ranges else []
        return replace(self, ids=ids if ids is not None else [self.ids[i] for i in idx.tolist()],
                       obs=self.obs[:, idx], inputs=self.inputs.select(idx), params=self.params[idx],
                       u0=self.u0[idx], split_time=self.split_time[idx], initial_ranges=ranges)


def make_batch(experiments: Sequence, model: CompiledModel, dtype: torch.dtype = torch.float64) -> Batch:
    """Stack loaded experiments (see :mod:`physmend.data`) into a :class:`Batch`."""
    if not experiments:
        raise ValueError("make_batch needs at least one experiment")
    t = np.unique(np.concatenate([np.asarray(e.obs_time, dtype=np.float64) for e in experiments]))
    n_out = len(model.output_names)
    obs = np.full((t.size, len(experiments), n_out), np.nan)
    for b, e in enumerate(experiments):
        rows = np.searchsorted(t, e.obs_time)
        obs[rows, b, :] = e.obs
    inputs = from_channels(
        [[(e.inputs[n].time, e.inputs[n].values) for n in model.input_names] for e in experiments], dtype
    )
    params = torch.as_tensor(np.stack([np.asarray(e.parameters, dtype=np.float64) for e in experiments]), dtype=dtype)
    u0 = model.start(params).clone()
    index = {n: i for i, n in enumerate(model.state_names)}
    for b, e in enumerate(experiments):
        for name, value in (e.initial or {}).items():
            u0[b, index[name]] = float(value)
    split = torch.tensor(
        [float(e.split_time) if e.split_time is not None else float("inf") for e in experiments], dtype=dtype
    )
    return Batch(
        ids=[str(e.id) for e in experiments],
        t=torch.as_tensor(t, dtype=dtype),
        obs=torch.as_tensor(obs, dtype=dtype),
        inputs=inputs,
        params=params,
        u0=u0,
        split_time=split,
        initial_ranges=[dict(getattr(e, "initial_ranges", None) or {}) for e in experiments],
    )


#: a clock per experiment is used where the busiest experiment's own stops are at most this share of
#: the shared axis's (its rows and input knots): an iteration with a clock each costs about 1.6
#: times a shared step (per-element times, inputs and step control)
CLOCKS_PAY_BELOW = 0.6


def own_stops(batch: Batch) -> list[torch.Tensor] | None:
    """Per experiment, the times (s) a solver on its own clock ends steps on: its rows with a
    measurement and the kinks of its own inputs (:meth:`PiecewiseLinear.kinks`); None where a
    clock each would not pay (one experiment, or experiments sampled at nearly the same times:
    :data:`CLOCKS_PAY_BELOW`)."""
    if batch.size < 2:
        return None
    measured = torch.isfinite(batch.obs).any(-1)  # (T, B)
    kinks = batch.inputs.kinks()
    own = [torch.unique(torch.cat([batch.t[measured[:, b]], kinks[b].to(batch.t.dtype)])) for b in range(batch.size)]
    shared = torch.unique(torch.cat([batch.t, batch.inputs.knots.to(batch.t.dtype)])).numel()
    return own if max(o.numel() for o in own) <= CLOCKS_PAY_BELOW * shared else None


def inputs_at(batch: Batch, t: torch.Tensor) -> torch.Tensor:
    """The inputs ``(B, m)`` at one time ``t`` (s, scalar), or each element at its own ``t (B,)``."""
    return batch.inputs.each(t) if isinstance(t, torch.Tensor) and t.ndim == 1 else batch.inputs(t)


@dataclass
class Trajectories:
    """Simulated trajectories on ``batch.t``: ``states (T, B, n_states)``, ``outputs (T, B, n_outputs)``,
    ``observed (T, B, n_observed)``, ``inputs (T, B, n_inputs)``."""

    states: torch.Tensor
    outputs: torch.Tensor
    observed: torch.Tensor
    inputs: torch.Tensor


def simulate_batch(
    model: CompiledModel,
    batch: Batch,
    *,
    method: str = "rosenbrock23",
    rtol: float = 1e-6,
    atol: float = 1e-6,
    options: dict | None = None,
    params: torch.Tensor | None = None,
    u0: torch.Tensor | None = None,
    box: tuple[torch.Tensor, torch.Tensor] | None = None,
    exact: bool = True,
) -> Trajectories:
    """Simulate the model as written for every experiment of ``batch`` in one batched solve.

    A model affine in every row (``A u + B x + c``), simulated without a gradient, is solved
    exactly over each input segment whatever ``method`` says (:mod:`physmend.simulate.affine`;
    ``exact=False``: by ``method``); where that solution leaves float range, by ``method``. A long
    record is solved in windows side by side where they join (:mod:`physmend.simulate.windows`).

    ``box = (lo, hi)``, each ``(B, n_states)``: the states are held inside it
    (:func:`physmend.simulate.divergence.projected`; one shared clock), so a model that blows up
    in finite time is simulated as written up to the box and held at its edge after.
    """
    p = batch.params if params is None else params
    options = dict(options or {})
    if box is not None:
        options["clocks"] = None  # the box is per batch element: every element on the shared clock
    knots = batch.inputs.knots
    inner = knots[(knots > batch.t[0]) & (knots < batch.t[-1])]
    if inner.numel():  # input kinks: step onto them rather than across them
        options.setdefault("tstops" if method in OWN_METHODS else "step_t", inner)

    if method in CLOCK_METHODS and "clocks" not in options:
        options["clocks"] = own_stops(batch)  # None: one shared clock
    rhs = model.bind(p)
    start = batch.u0 if u0 is None else u0
    states = None
    if exact and box is None and isinstance(rhs, BoundRhs):
        from physmend.simulate.affine import exact_affine

        states = exact_affine(rhs, batch.inputs, start, batch.t)
    if states is None and box is None:
        from physmend.simulate.windows import solve_in_windows

        states = solve_in_windows(rhs, batch.inputs, start, batch.t, method=method, rtol=rtol, atol=atol, options=options)
    if states is None:
        if box is not None:
            from physmend.simulate.divergence import projected

            rhs = projected(rhs, box[0], box[1])

        def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
            return rhs(u, inputs_at(batch, t))

        states = odeint(f, start, batch.t, method=method, rtol=rtol, atol=atol, options=options, names=batch.ids)
    x = batch.inputs.at(batch.t)
    return Trajectories(
        states=states,
        outputs=model.outputs(states, x, p[None]),
        observed=model.observed(states, x, p[None]),
        inputs=x,
    )
