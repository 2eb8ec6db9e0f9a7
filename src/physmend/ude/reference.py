"""The model as written, simulated on every experiment (the reference the network's inputs are
normalised from), the solver options, and the training/validation sample masks. Imports ``simulate``;
of ``physmend.ude`` only ``measured`` (lazily, for a bounded reference).

A model as written that diverges within the record (:mod:`physmend.simulate.divergence`) is no
reference for training as it stands; :func:`reference` with ``bounded=True`` (training's) then
keeps it within the data: see :func:`bounded_states`. A model that does not diverge gets exactly
the reference it always got.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
import dataclasses
import math

import torch

from physmend.problem import Problem
from physmend.simulate import Batch, SimulationError, make_batch, odeint
from physmend.simulate.batch import inputs_at, own_stops
from physmend.simulate.core import CLOCK_METHODS, OWN_METHODS
from physmend.simulate.divergence import Divergence, box_of, first_exits, projected, recorded_range
from physmend.simulate.initial import estimate_initial, has_unknown


@dataclass
class Reference:
    """The model as written, simulated on every experiment (no gradients)."""

    batch: Batch
    states: torch.Tensor  # (T, B, n)
    derivs: torch.Tensor  # (T, B, n)
    inputs: torch.Tensor  # (T, B, m)
    observed: torch.Tensor  # (T, B, k)
    #: where the model as written leaves the records' range (empty: it does not; only a bounded
    #: reference looks); the states from then on are the bounded ones (:func:`bounded_states`)
    divergence: list[Divergence] = field(default_factory=list)


def solver_options(cfg: Any) -> dict[str, Any]:
    """The whole-trajectory solver options of ``cfg.simulate`` (checked: :class:`physmend.settings.SimulateSettings`)."""
    from physmend.settings import SimulateSettings, TrainingSettings

    if isinstance(cfg, TrainingSettings):
        return cfg.simulate.solver()
    return SimulateSettings.build(cfg.simulate).solver()


def _kinks(batch: Batch, method: str) -> dict[str, Any]:
    knots = batch.inputs.knots
    inner = knots[(knots > batch.t[0]) & (knots < batch.t[-1])]
    if not inner.numel():
        return {}
    return {"tstops": inner} if method in OWN_METHODS else {"step_t": inner}


def simulate_with(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], batch: Batch, u0: torch.Tensor, sim: dict[str, Any],
                  jac: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Whole-trajectory simulation of ``rhs(u, x)`` on ``batch``: states ``(T, B, n)``.

    ``jac(u, x)``: the exact ``d rhs / du (B, n, n)``, used by the stiff solver instead of finite
    differences (which cost ``n`` extra right-hand sides per step).
    """
    options = {**_kinks(batch, sim["method"]), **sim["options"]}
    if sim["method"] in CLOCK_METHODS and "clocks" not in options:
        options["clocks"] = own_stops(batch)  # each experiment steps on its own times only (None: shared)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return rhs(u, inputs_at(batch, t))

    if jac is not None and sim["method"] in OWN_METHODS and "jacobian" not in options:
        options["jacobian"] = lambda t, u: jac(u, inputs_at(batch, t))
    elif not torch.is_grad_enabled():  # a long record: in windows side by side where they join
        from physmend.simulate.windows import solve_in_windows

        states = solve_in_windows(rhs, batch.inputs, u0, batch.t, method=sim["method"], rtol=sim["rtol"],
                                  atol=sim["atol"], options=options)
        if states is not None:
            return states

    return odeint(f, u0, batch.t, method=sim["method"], rtol=sim["rtol"], atol=sim["atol"], options=options, names=batch.ids)


def with_stops(sim: dict[str, Any], batch: Batch) -> dict[str, Any]:
    """``sim`` with the clocks :func:`simulate_with` would give ``batch`` fixed in its options: for a
    solve of ``batch``'s rows whose inputs are replaced by a function of them with the same knots (a
    drive, :func:`physmend.ude.drive.drive_table`), so that its steps end where they end on ``batch``."""
    if sim["method"] not in CLOCK_METHODS or "clocks" in sim["options"]:
        return sim
    return {**sim, "options": {**sim["options"], "clocks": own_stops(batch)}}


def clocked(sim: dict[str, Any], batch: Batch) -> bool:
    """Whether a solve of ``batch`` with the solver options ``sim`` gives each row its own clock
    (:func:`simulate_with`): each row then takes the steps it takes alone, and one solve of several
    records (or of several models' rows) costs what its busiest row needs (the cargo box's two
    records, a stack of two models: 2.0 s a checkpoint against 2.5 s solved per time grid)."""
    return sim["method"] in CLOCK_METHODS and "clocks" not in sim["options"] and own_stops(batch) is not None


def reference(problem: Problem, cfg: Any, *, bounded: bool = False, shared_clock: bool = True) -> Reference:
    """The model as written simulated on every experiment of ``problem`` (no gradients).

    ``bounded``: a reference for training — where the model as written diverges (an output leaves
    its box, :mod:`physmend.simulate.divergence`, or the solve fails as it blows up) the states
    are kept within the data (:func:`bounded_states`) and the finding is ``divergence``. Without
    it (the default: a corrected model judged by its simulation) a failing solve raises and a
    diverging one returns what it gives.

    ``shared_clock``: every experiment's steps end on every row of the shared time axis (the
    default: training's reference, whose values there are the network's normalisation and the
    segment starts); False: each experiment's steps end on its own times only (as
    :func:`simulate_with` does), the rows of the others' times interpolated — for a model judged
    against its records (the cargo box's corrected model: 2.7 s against 4.7 s, its three records
    sampled at different times; the outputs at the records' times agree within the tolerances).

    Raises:
        SimulationError: a training or validation experiment cannot be simulated (bounded: nor
            within the box of its records).
    """
    model = problem.compiled
    batch = make_batch(problem.experiments, model, problem.dtype)

    # one shared clock: the reference's values at every row of the shared axis (the network's
    # normalisation, segment starts of hidden states) are the method's step ends, not interpolants
    sim = solver_options(cfg)
    if shared_clock:
        sim = {**sim, "options": {**sim["options"], "clocks": None}}

    def outputs(sub: Batch, u0: torch.Tensor) -> torch.Tensor:
        states = simulate_with(model.bind(sub.params), sub, u0, sim, model.jacobian(sub.params))
        return model.outputs(states, sub.inputs.at(sub.t), sub.params[None])

    def solve(sub: Batch) -> torch.Tensor:
        rhs = model.bind(sub.params)
        return simulate_with(rhs, sub, sub.u0, sim, model.jacobian(sub.params))

    with torch.no_grad():
        if has_unknown(batch):  # declared-unknown initial values: the model as written's own estimates
            batch = dataclasses.replace(batch, u0=estimate_initial(outputs, batch, model.state_names))
        found: list[Divergence] = []
        if bounded:
            states, found = bounded_states(problem, batch, solve, sim)
        else:
            states = held_out_apart(problem, batch, solve)
        rhs = model.bind(batch.params)
        x = batch.inputs.at(batch.t)
        derivs = rhs(states, x)
        observed = model.observed(states, x, batch.params[None])
    return Reference(batch, states, derivs, x, observed, found)


def _fitted(problem: Problem) -> torch.Tensor:
    """``(B,)`` True for the training and validation experiments (the records a range comes from)."""
    return torch.tensor([e.role in ("train", "validation") for e in problem.experiments])


def output_boxes(problem: Problem, batch: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(lo, hi, box_lo, box_hi)``, each ``(k,)``: every output's recorded range over the fitted
    experiments and its box (:func:`physmend.simulate.divergence.box_of`)."""
    lo, hi = recorded_range(batch.obs, _fitted(problem))
    return (lo, hi, *box_of(lo, hi))


def state_boxes(problem: Problem, batch: Batch, box_lo: torch.Tensor, box_hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(B, n)``: the box of every state an output measures (``y = g(p)·x``:
    the output's box divided by ``g`` of each experiment; the narrowest where several do), ``∓inf``
    for a state no output measures."""
    from physmend.ude.measured import factors, measured_outputs

    B, n = batch.u0.shape
    lo = torch.full((B, n), -math.inf, dtype=batch.u0.dtype)
    hi = torch.full((B, n), math.inf, dtype=batch.u0.dtype)
    g = factors(problem.model)(batch.params)  # (B, q)
    for c, (j, i, _) in enumerate(measured_outputs(problem.model)):
        a, b = box_lo[j] / g[:, c], box_hi[j] / g[:, c]
        lo[:, i] = torch.maximum(lo[:, i], torch.minimum(a, b).nan_to_num(nan=-math.inf))
        hi[:, i] = torch.minimum(hi[:, i], torch.maximum(a, b).nan_to_num(nan=math.inf))
    return lo, hi


def find_divergence(problem: Problem, batch: Batch, outputs: torch.Tensor, blows_up: bool = False) -> list[Divergence]:
    """Every experiment's outputs ``(T, B, k)`` that diverge within its own record, one
    :class:`Divergence` per experiment and output, earliest first: an output that is not finite,
    or leaves its box and is still leaving it at the record's end (:func:`_still_leaving`).
    ``blows_up``: the outputs come from a solve held in the box because the plain one failed —
    reaching the box's edge counts."""
    from physmend.ude.measured import measured_outputs

    lo, hi, box_lo, box_hi = output_boxes(problem, batch)
    if blows_up:  # a projected solve stops at the edge: reaching it is leaving
        eps = 1e-6 * (hi - lo).nan_to_num(nan=0.0)
        box_lo, box_hi = box_lo + eps, box_hi - eps
    ends = torch.tensor([float(e.obs_time[-1]) for e in problem.experiments], dtype=batch.t.dtype)
    valid = batch.t[:, None] <= ends[None, :]  # (T, B): within each experiment's own record
    first = first_exits(outputs, box_lo, box_hi, valid)
    measures = {j: problem.model.state_names[i] for j, i, _ in measured_outputs(problem.model)}
    names = problem.model.output_names
    found = []
    for b, j in torch.nonzero(first >= 0).tolist():
        row = int(first[b, j])
        rows = valid[:, b]
        y = outputs[rows, b, j]
        finite = bool(torch.isfinite(y).all())
        if finite and not blows_up and not _still_leaving(y, box_lo[j], box_hi[j]):
            continue  # out and back (or turned): a model that misses, not one that diverges
        peak = math.inf if blows_up or not finite else float(y.abs().max())
        e = problem.experiments[b]
        found.append(Divergence(experiment=str(e.id), role=e.role, name=measures.get(j, names[j]), output=names[j],
                                time=float(batch.t[row]), blows_up=blows_up, low=float(lo[j]), high=float(hi[j]),
                                box_low=float(box_lo[j]), box_high=float(box_hi[j]), value=float(outputs[row, b, j]),
                                peak=peak, end=float(ends[b])))
    return sorted(found, key=lambda d: (d.time, d.experiment, d.output))


def _still_leaving(y: torch.Tensor, box_lo: torch.Tensor, box_hi: torch.Tensor) -> bool:
    """True where ``y (T,)`` (one experiment's output within its record) ends outside its box at
    its farthest excursion: it left the records' range and is still leaving it when the record
    ends. A simulation that went out and came back, or turned, misses the records but has not
    diverged (a model as written that is wrong but bounded keeps its reference)."""
    beyond = torch.maximum(box_lo - y, y - box_hi).clamp_min(0.0)
    return bool(beyond[-1] > 0) and bool(beyond[-1] >= beyond.max())


def bounded_states(problem: Problem, batch: Batch, solve: Callable[[Batch], torch.Tensor],
                   sim: dict[str, Any]) -> tuple[torch.Tensor, list[Divergence]]:
    """States ``(T, B, n)`` of the model as written kept within the data, and where it diverges.

    The model as written is solved as always; where no output leaves its box, that is the answer
    (bit for bit). Where the solve fails, it is solved again held inside the boxes of the measured
    states (:func:`physmend.simulate.divergence.projected`): exactly as written until it reaches
    one (a finite-time blow-up), held there after. Where an output leaves its box (first row ``r``
    of an experiment), from ``r`` on the experiment's measured states are their records (training
    and validation experiments: linearly interpolated, divided by the output's factor) or held in
    their box (test experiments: their records decide nothing), and every other state keeps its
    last value before ``r``. The reference then lies within the data: the network's normalisation,
    the training box, the time step from its Jacobian and the segment starts all come from it.

    Raises:
        SimulationError: the plain solve failed and the held one failed as well, or reached no box
            (the failure is not a divergence): the plain solve's error.
    """
    model = problem.compiled
    p = batch.params[None]
    try:
        states = held_out_apart(problem, batch, solve)
        blows_up = False
    except SimulationError as exc:
        _, _, box_lo, box_hi = output_boxes(problem, batch)
        lo, hi = state_boxes(problem, batch, box_lo, box_hi)
        if not bool((torch.isfinite(lo) | torch.isfinite(hi)).any()):
            raise
        rhs_of = model.bind

        def held(sub: Batch) -> torch.Tensor:
            idx = [batch.ids.index(i) for i in sub.ids]
            return simulate_with(projected(rhs_of(sub.params), lo[idx], hi[idx]), sub, sub.u0, sim)

        try:
            states = held_out_apart(problem, batch, held)
        except SimulationError:
            raise exc from None
        blows_up = True
        failure = exc
    x = batch.inputs.at(batch.t)
    found = find_divergence(problem, batch, model.outputs(states, x, p), blows_up)
    if not found:
        if blows_up:
            raise failure
        return states, []
    return _within_data(problem, batch, states, found), found


def _within_data(problem: Problem, batch: Batch, states: torch.Tensor, found: list[Divergence]) -> torch.Tensor:
    """``states (T, B, n)`` with every diverging experiment's rows from its first divergence on
    replaced as :func:`bounded_states` says."""
    import numpy as np

    from physmend.ude.measured import factors, measured_outputs

    out = states.clone()
    t = batch.t
    _, _, box_lo, box_hi = output_boxes(problem, batch)
    lo, hi = state_boxes(problem, batch, box_lo, box_hi)
    g = factors(problem.model)(batch.params)
    first: dict[str, float] = {}
    for d in found:
        first[d.experiment] = min(first.get(d.experiment, math.inf), d.time)
    tn = t.cpu().numpy()
    for b, exp in enumerate(problem.experiments):
        if str(exp.id) not in first:
            continue
        r = int(torch.searchsorted(t, torch.tensor(first[str(exp.id)], dtype=t.dtype)))
        last = out[r - 1, b] if r > 0 else batch.u0[b]
        last = torch.where(torch.isfinite(last), last, batch.u0[b])
        out[r:, b] = last  # every state: its last value before the divergence
        out[r:, b] = torch.clamp(out[r:, b], lo[b], hi[b])
        if exp.role == "test":
            continue  # measured states held in their box: a test record decides nothing
        for c, (j, i, _) in enumerate(measured_outputs(problem.model)):
            y = batch.obs[:, b, j].cpu().numpy()
            ok = np.isfinite(y)
            if not ok.any():
                continue
            rec = np.interp(tn[r:], tn[ok], y[ok])
            out[r:, b, i] = torch.as_tensor(rec, dtype=out.dtype) / g[b, c]
    return out


def held_out_apart(problem: Problem, batch: Batch, solve: Callable[[Batch], torch.Tensor]) -> torch.Tensor:
    """``solve(batch)`` — a whole-trajectory quantity ``(T, B, ...)`` — on every experiment, such that
    test experiments decide nothing: when the one solve fails, the training and validation
    experiments are solved together (their failure is raised) and each test experiment alone; a
    test experiment whose solve fails is NaN throughout.
    """
    try:
        return solve(batch)
    except SimulationError as exc:
        first = exc
        test = [i for i, e in enumerate(problem.experiments) if e.role == "test"]
        if not test:
            raise
    kept = [i for i in range(batch.size) if i not in test]
    u0 = {int(i): batch.u0[i] for i in range(batch.size)}
    out: torch.Tensor | None = None
    for group in [kept] + [[i] for i in test]:
        if not group:
            continue
        sub = make_batch([problem.experiments[i] for i in group], problem.compiled, problem.dtype)
        sub = dataclasses.replace(sub, u0=torch.stack([u0[i] for i in group]))  # estimated starts stay
        try:
            part = solve(sub)
        except SimulationError:
            if group is kept:
                raise
            continue  # NaN: the report counts it (test.failed)
        if out is None:
            out = torch.full((batch.t.shape[0], batch.size, *part.shape[2:]), math.nan, dtype=part.dtype)
        out[:, torch.tensor(group)] = on_axis(part, sub.t, batch.t)
    if out is None:  # only test experiments, and none could be solved
        raise first
    return out


def on_axis(values: torch.Tensor, t_from: torch.Tensor, t_to: torch.Tensor) -> torch.Tensor:
    """``values (T1, ...)`` at the times ``t_from (T1,)`` (ascending), linearly interpolated to the
    times ``t_to (T2,)``: ``(T2, ...)``, NaN outside ``t_from``'s span (a group solved apart has no
    rows at the other experiments' sample times; every row of the shared axis needs its value)."""
    k = torch.searchsorted(t_from, t_to).clamp(1, max(t_from.shape[0] - 1, 1))
    if t_from.shape[0] == 1:
        out = values[torch.zeros_like(k)]
    else:
        t0, t1 = t_from[k - 1], t_from[k]
        w = ((t_to - t0) / (t1 - t0)).reshape(-1, *([1] * (values.dim() - 1))).to(values.dtype)
        out = values[k - 1] + w * (values[k] - values[k - 1])
    outside = (t_to < t_from[0]) | (t_to > t_from[-1])
    return torch.where(outside.reshape(-1, *([1] * (values.dim() - 1))), torch.nan, out)


def train_mask(problem: Problem, batch: Batch) -> torch.Tensor:
    """``(T, B)`` True where a time belongs to a training sample (train role, before the split)."""
    roles = torch.tensor([e.role == "train" for e in problem.experiments])
    return (batch.t[:, None] < batch.split_time[None, :]) & roles[None, :]


def _val_mask(problem: Problem, batch: Batch) -> torch.Tensor:
    if any(e.role == "validation" for e in problem.experiments):
        roles = torch.tensor([e.role == "validation" for e in problem.experiments])
        return roles[None, :].expand(batch.t.shape[0], -1).clone()
    roles = torch.tensor([e.role == "train" for e in problem.experiments])
    return (batch.t[:, None] >= batch.split_time[None, :]) & roles[None, :]


def _stats(values: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and std over masked ``(T, B)`` entries of ``values (T, B, k)``; std floored."""
    v = values[mask]
    mean = v.mean(0)
    std = v.std(0) if v.shape[0] > 1 else torch.ones_like(mean)
    floor = 1e-3 * mean.abs().clamp_min(1.0)
    return mean, torch.where(std < floor, torch.maximum(floor, torch.ones_like(std) * (std < 1e-12)), std)
