"""Initial values declared unknown (``initial: {state: [low, high]}`` in the data config), estimated
per experiment from the start of its own record.

An unmeasured state's value at the start of a recording is rarely known (the level in a tank
nobody reads, the polarisation a cell kept from its last load). Whoever simulates a model — the
model as written, a hybrid at a checkpoint, a candidate formula — estimates it the same way: the
value within the declared range whose simulated outputs best match the first
:data:`WINDOW_FRACTION` of the experiment's measured record (at least :data:`MIN_SAMPLES` samples),
found by a batched search (every candidate of every experiment in one solve: the whole declared box,
then a few rounds of finer boxes around the best :data:`KEEP`). It is a function of the model and the record alone, so validation and
test experiments get theirs from their own opening window, exactly as a user's observer would;
their remaining record is what the fit is judged on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math

import torch

from physmend.simulate.batch import Batch
from physmend.simulate.errors import SimulationError

#: share of each record, from its first measured sample, that its unknown initial values are fitted on
WINDOW_FRACTION = 0.05
#: weights fall as ``exp(-DECAY · age)`` over the window (age 0 at its first sample, 1 at its last):
#: the opening counts most, and a start that fits the window's end only by absorbing what the model
#: leaves out does not win
DECAY = 4.0
#: fewest measured samples in that window (short records use more of themselves)
MIN_SAMPLES = 10
#: candidates per experiment in the first round: a grid of 17 for one unknown, a Sobol set twice as
#: large per further unknown (at most :data:`MAX_FIRST`)
FIRST_ROUND = 17
MAX_FIRST = 129
#: best candidates of each experiment kept and searched around in each refining round (an opening
#: window can fit well at more than one start: an oscillation's phase, say)
KEEP = 2
#: each refining round samples one spacing either side of each kept candidate (a 3-point grid per
#: unknown up to :data:`GRID_UP_TO` unknowns), then divides the spacing by :data:`SHRINK`: the best
#: of a round lies within half a spacing of the optimum, inside the next round's reach
SHRINK = 2.0
GRID_UP_TO = 3
#: refining rounds (one unknown: range/16 → range/1024 at the end)
ROUNDS = 6
#: rounds of a search about an earlier estimate (``near``)
LOCAL_ROUNDS = 3

#: ``solve(rows, u0)``: outputs ``(T, R, k)`` of the model on the batch elements ``rows`` started at ``u0 (R, n)``
Solve = Callable[[Batch, torch.Tensor], torch.Tensor]


def has_unknown(batch: Batch) -> bool:
    """True when some experiment of ``batch`` declares an unknown initial value."""
    return any(batch.initial_ranges)


def estimate_initial(solve: Solve, batch: Batch, state_names: Sequence[str], *, isolate: bool = True,
                     near: torch.Tensor | None = None) -> torch.Tensor:
    """``batch.u0 (B, n)`` with every declared-unknown initial value replaced by its estimate.

    ``near (B, n)``: an earlier estimate of a model that has changed little since (the same hybrid
    at its previous checkpoint): the search skips the whole-range round and refines about it over
    :data:`LOCAL_ROUNDS` rounds, the last rounds of a full search (it follows an estimate that moved
by up to about 1/30 of the range since).

    Experiments with nothing unknown keep their ``u0`` (and cost nothing). A candidate whose
    simulation fails scores infinitely badly (``isolate``: the failed solve is repeated per
    experiment, then per candidate; otherwise the :class:`SimulationError` propagates); when every
    candidate of an experiment fails, its start stays mid-range.
    """
    u0 = batch.u0.clone()
    if not has_unknown(batch):
        return u0
    index = {n: i for i, n in enumerate(state_names)}
    unknown = {b: [(index[s], float(lo), float(hi)) for s, (lo, hi) in ranges.items()]
               for b, ranges in enumerate(batch.initial_ranges) if ranges}
    todo = sorted(unknown)
    window, weight = _window(batch, todo)
    spread = _spread(window.obs[:, todo])
    # always KEEP per experiment (the best repeated where fewer succeed): every experiment gets the
    # same number of candidates in every call, whatever failed (stacked callers rely on the layout)
    kept: dict[int, list[torch.Tensor]] = {b: [u0[b].clone()] * KEEP for b in todo}
    spacing: dict[int, torch.Tensor] = {}
    first = 0
    if near is not None:
        first = ROUNDS + 1 - LOCAL_ROUNDS
        for b in todo:
            kept[b] = [near[b].clone().to(u0.dtype)] * KEEP
            spacing[b] = _first_round(unknown[b])[1] / SHRINK ** (first - 1)  # as a full search has it by then
    with torch.no_grad():
        for r in range(first, ROUNDS + 1):
            rows: list[int] = []
            starts: list[torch.Tensor] = []
            for b in todo:
                cols = [i for i, _, _ in unknown[b]]
                if r == 0:
                    values, spacing[b] = _first_round(unknown[b])
                else:
                    values = _around(unknown[b], [k[cols] for k in kept[b]], spacing[b])
                    spacing[b] = spacing[b] / SHRINK
                for v in values:
                    start = kept[b][0].clone()
                    start[cols] = v.to(u0.dtype)
                    rows.append(b)
                    starts.append(start)
            errors = _scores(solve, window, rows, torch.stack(starts), weight, spread, isolate)
            for b in todo:
                mine = [j for j, row in enumerate(rows) if row == b]
                scores = errors[mine]
                good = [mine[int(j)] for j in torch.argsort(scores) if bool(torch.isfinite(scores[j]))]
                if good:
                    kept[b] = [starts[j] for j in (good + [good[0]] * KEEP)[:KEEP]]
    for b in todo:
        u0[b] = kept[b][0]
    return u0


def _first_round(entries: list[tuple[int, float, float]]) -> tuple[list[torch.Tensor], torch.Tensor]:
    """Candidates over the whole declared box (one unknown: a grid; several: a Sobol set and the
    centre among them, deterministic) and their typical spacing ``(d,)``."""
    d = len(entries)
    lo = torch.tensor([e[1] for e in entries], dtype=torch.float64)
    hi = torch.tensor([e[2] for e in entries], dtype=torch.float64)
    if d == 1:
        unit = torch.linspace(0.0, 1.0, FIRST_ROUND, dtype=torch.float64)[:, None]
        per_axis = FIRST_ROUND - 1
    else:
        n = min(MAX_FIRST, FIRST_ROUND * 2 ** (d - 1))
        unit = torch.quasirandom.SobolEngine(d, scramble=False).draw(n, dtype=torch.float64)  # corner, centre, …
        per_axis = max(1.0, n ** (1.0 / d) - 1)
    return list(lo + unit * (hi - lo)), (hi - lo) / per_axis


def _around(entries: list[tuple[int, float, float]], centres: list[torch.Tensor], spacing: torch.Tensor
            ) -> list[torch.Tensor]:
    """Candidates about each centre, one ``spacing`` either side along each unknown, kept inside the
    declared box: the full 3-point grid (``3^d``) up to :data:`GRID_UP_TO` unknowns, 27 Sobol points
    (the centre among them) beyond."""
    d = len(entries)
    lo = torch.tensor([e[1] for e in entries], dtype=torch.float64)
    hi = torch.tensor([e[2] for e in entries], dtype=torch.float64)
    if d <= GRID_UP_TO:
        axes = torch.meshgrid(*[torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)] * d, indexing="ij")
        unit = torch.stack([a.flatten() for a in axes], -1)
    else:
        unit = torch.quasirandom.SobolEngine(d, scramble=False).draw(27, dtype=torch.float64) * 2.0 - 1.0  # corner, centre, …
    out: list[torch.Tensor] = []
    for c in centres:
        points = torch.minimum(hi, torch.maximum(lo, c.to(torch.float64) + unit * spacing))
        out.extend(points)
    return out


def _window(batch: Batch, todo: list[int]) -> tuple[Batch, torch.Tensor]:
    """The batch cut to the longest opening window of ``todo``, and ``(Tw, B)`` weights: 1 on each
    experiment's own measured window samples."""
    measured = torch.isfinite(batch.obs).any(-1)  # (T, B)
    ends = torch.full((batch.size,), -math.inf, dtype=batch.t.dtype)
    begins = torch.zeros((batch.size,), dtype=batch.t.dtype)
    for b in todo:
        times = batch.t[measured[:, b]]
        if times.numel() == 0:
            continue
        end = times[0] + WINDOW_FRACTION * (times[-1] - times[0])
        ends[b] = torch.maximum(end, times[min(MIN_SAMPLES, times.numel()) - 1])
        begins[b] = times[0]
    last = int(torch.searchsorted(batch.t, ends.max(), right=True))
    inside = measured[:last] & (batch.t[:last, None] <= ends[None, :])
    # the opening counts most: what the model leaves out has had the least time to pull it away there
    age = (batch.t[:last, None] - begins[None, :]) / (ends - begins).clamp_min(1e-300)[None, :]
    weight = torch.where(inside, torch.exp(-DECAY * age), torch.zeros_like(age))
    cut = Batch(ids=batch.ids, t=batch.t[:last], obs=batch.obs[:last], inputs=batch.inputs, params=batch.params,
                u0=batch.u0, split_time=batch.split_time, initial_ranges=batch.initial_ranges)
    return cut, weight


def _spread(obs: torch.Tensor) -> torch.Tensor:
    """Per-output spread ``(k,)`` of the measured window values (outputs of different units weigh alike)."""
    out = []
    for j in range(obs.shape[-1]):
        v = obs[..., j][torch.isfinite(obs[..., j])]
        s = float(v.std()) if v.numel() > 1 else 0.0
        out.append(s if s > 1e-12 else max(1e-12, float(v.abs().mean()) if v.numel() else 1.0))
    return torch.tensor(out, dtype=obs.dtype)


def _scores(solve: Solve, window: Batch, rows: list[int], starts: torch.Tensor, weight: torch.Tensor,
            spread: torch.Tensor, isolate: bool) -> torch.Tensor:
    """Mean squared scaled output error ``(R,)`` of each candidate over its experiment's window;
    inf where its simulation failed. One solve; on failure, one per experiment, then one per candidate."""
    try:
        return _score(solve(window.take(rows), starts), window, rows, weight, spread)
    except SimulationError:
        if not isolate:
            raise
    out = torch.full((len(rows),), math.inf, dtype=starts.dtype)
    for b in sorted(set(rows)):
        mine = [j for j, row in enumerate(rows) if row == b]
        try:
            out[mine] = _score(solve(window.take([b] * len(mine)), starts[mine]), window, [b] * len(mine), weight, spread)
            continue
        except SimulationError:
            pass
        for j in mine:
            try:
                out[j] = _score(solve(window.take([b]), starts[j:j + 1]), window, [b], weight, spread)[0]
            except SimulationError:
                pass
    return out


def _score(y: torch.Tensor, window: Batch, rows: list[int], weight: torch.Tensor, spread: torch.Tensor) -> torch.Tensor:
    idx = torch.tensor(rows)
    err = ((y - window.obs[:, idx]) / spread).pow(2)  # (Tw, R, k)
    err = torch.where(torch.isfinite(window.obs[:, idx]), err, torch.zeros_like(err))
    w = weight[:, idx]
    total = (err.sum(-1) * w).sum(0) / w.sum(0).clamp_min(1.0)
    return torch.where(torch.isfinite(total), total, torch.full_like(total, math.inf))
