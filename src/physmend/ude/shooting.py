"""Multiple shooting: the plan of segments over the training records, fixed-step RK4 over all
segments at once, chained segment starts, and the scales of the loss. Imports ``hybrid``,
``reference`` (and ``timescale``, lazily).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any
import math

import numpy as np
import torch

from physmend.problem import Problem
from physmend.simulate import Batch
from physmend.ude.hybrid import HybridSpec, UDEConfigError, der_coefficients
from physmend.ude.reference import Reference


@dataclass
class Shooting:
    """Segments of all training records on a uniform grid of step ``dt`` (s)."""

    dt: float
    steps: int  # grid steps per segment
    exp_index: torch.Tensor  # (S,) batch element of each segment
    first: torch.Tensor  # (S,) True for the first segment of an experiment
    starts: torch.Tensor  # (S,) start time (s)
    x_half: torch.Tensor  # (2*steps+1, S, m) inputs at every half step
    obs_k: torch.Tensor  # (N,) grid interval of each observation
    obs_w: torch.Tensor  # (N,) linear weight within the interval
    obs_s: torch.Tensor  # (N,) segment of each observation
    obs_j: torch.Tensor  # (N,) output index
    obs_y: torch.Tensor  # (N,) measured value
    next_of: torch.Tensor  # (S,) index of the following segment of the same experiment, -1 if last


def plan_shooting(problem: Problem, batch: Batch, cfg: Any) -> Shooting:
    from physmend.settings import training_settings
    from physmend.ude.timescale import resolve_settings

    cfg = resolve_settings(training_settings(cfg), problem)
    dt = float(cfg.train.step)
    seg = float(cfg.train.segment_length)
    if not (dt > 0 and seg >= dt):
        raise UDEConfigError(f"train.step and train.segment_length need 0 < step <= segment_length, but got ({dt}, {seg})")
    steps = int(round(seg / dt))
    dtype = batch.t.dtype
    exp_idx, first, starts = [], [], []
    obs: list[tuple[int, int, float, int, float]] = []
    for b, e in enumerate(problem.experiments):
        if e.role != "train":
            continue
        end = float(e.split_time) if e.split_time is not None else float(e.obs_time[-1])
        n_seg = max(1, math.ceil(end / (steps * dt) - 1e-9))
        base = len(starts)
        for k in range(n_seg):
            exp_idx.append(b)
            first.append(k == 0)
            starts.append(k * steps * dt)
        for i, tt in enumerate(e.obs_time):
            if tt >= end and e.split_time is not None:
                break
            s = min(int(tt // (steps * dt)), n_seg - 1)
            local = (tt - starts[base + s]) / dt
            k = min(int(local), steps - 1)
            for j in range(e.obs.shape[1]):
                y = e.obs[i, j]
                if np.isfinite(y):
                    obs.append((base + s, k, local - k, j, float(y)))
    S = len(starts)
    if S == 0:
        raise UDEConfigError("training needs at least one experiment with role 'train'")
    from physmend.ude.timescale import check_steps

    check_steps(steps, S, dt, problem, [cfg])  # before the grid (2·steps + 1, S) is built
    exp_t = torch.tensor(exp_idx)
    start_t = torch.tensor(starts, dtype=dtype)
    grid = start_t[None, :] + torch.arange(2 * steps + 1, dtype=dtype)[:, None] * (dt / 2)  # (2K+1, S)
    x_half = batch.inputs.select(exp_t).at_each(grid)  # (2K+1, S, m): each segment's own inputs
    next_of = torch.full((S,), -1, dtype=torch.long)
    for s in range(S - 1):
        if exp_idx[s + 1] == exp_idx[s] and not first[s + 1]:
            next_of[s] = s + 1
    o = list(zip(*obs))
    return Shooting(
        dt=dt,
        steps=steps,
        exp_index=exp_t,
        first=torch.tensor(first),
        starts=start_t,
        x_half=x_half,
        obs_s=torch.tensor(o[0]),
        obs_k=torch.tensor(o[1]),
        obs_w=torch.tensor(o[2], dtype=dtype),
        obs_j=torch.tensor(o[3]),
        obs_y=torch.tensor(o[4], dtype=dtype),
        next_of=next_of,
    )


def rk4_segments(rhs: Callable[[torch.Tensor, Any], torch.Tensor], u0: torch.Tensor, plan: Shooting,
                 box: tuple[torch.Tensor, torch.Tensor] | None = None, drives: Any = None) -> torch.Tensor:
    """Fixed-step RK4 over all segments at once: states at grid points ``(steps+1, S, n)``.

    ``box = (lo, hi)``, each ``(n,)``: every stage's state is held inside it (:func:`state_box`), so
    a segment that a half-trained correction sends off to infinity (a population pushed below zero
    into a quadratic loss, say) stays finite: it fits badly, and the other segments still train.
    ``drives``: what ``rhs`` takes at each half step instead of the inputs ``plan.x_half``
    (:class:`physmend.ude.drive.Drives`).
    """
    h = plan.dt
    xs = plan.x_half if drives is None else drives
    hold = (lambda v: v) if box is None else (lambda v: torch.clamp(v, box[0], box[1]))
    u = u0
    out = [u]
    for k in range(plan.steps):
        x0, xm, x1 = xs[2 * k], xs[2 * k + 1], xs[2 * k + 2]
        k1 = rhs(u, x0)
        k2 = rhs(hold(torch.add(u, k1, alpha=0.5 * h)), xm)
        k3 = rhs(hold(torch.add(u, k2, alpha=0.5 * h)), xm)
        k4 = rhs(hold(torch.add(u, k3, alpha=h)), x1)
        u = hold(torch.add(u, torch.add(k1, torch.add(k2, k3), alpha=2.0).add_(k4), alpha=h / 6.0))
        out.append(u)
    return torch.stack(out)


#: the training solve holds each state within this many training ranges beyond its training range
#: (:meth:`~physmend.ude.hybrid.HybridSpec.box`); a model as written that goes farther beyond the
#: records' range diverges (:data:`physmend.simulate.divergence.RANGE_MARGIN`, the same number)
BOX_MARGIN = 3.0


def chained_starts(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], u0: torch.Tensor, plan: Shooting,
                   models: int = 1, keep: Sequence[int] = ()) -> torch.Tensor:
    """Segment starts chained by ``rhs``: every segment after an experiment's first starts where
    ``rhs`` takes the one before it (fixed-step RK4 on the training grid, no gradients), except in
    the state columns ``keep`` (e.g. measured states, which start at their records).

    With ``keep`` empty this is single shooting: no gaps at all. ``u0 (models·S, n)``: starts of
    ``models`` stacked copies of the plan's ``S`` segments, rows model-major (``rhs`` and
    ``plan.x_half`` cover all rows); first segments keep theirs. A model whose chained trajectory
    leaves the finite range keeps its ``u0`` rows. Costs one RK4 pass over all segments per segment
    of the longest experiment.
    """
    S = plan.next_of.shape[0]
    has = plan.next_of >= 0
    if not bool(has.any()):
        return u0.clone()
    offsets = (torch.arange(models) * S)[:, None]
    src = (torch.nonzero(has).flatten()[None] + offsets).flatten()
    dst = (plan.next_of[has][None] + offsets).flatten()
    depth = int(torch.bincount(plan.exp_index).max())
    with torch.no_grad():
        u = u0.clone()
        cols = torch.tensor([i for i in range(u.shape[-1]) if i not in set(keep)], dtype=torch.long)
        for _ in range(depth - 1):
            end = rk4_segments(rhs, u, plan)[-1][src]
            u[dst[:, None], cols[None, :]] = end[:, cols]
        ok = torch.isfinite(u).reshape(models, -1).all(dim=1).repeat_interleave(S)
        return torch.where(ok[:, None], u, u0)


def segments_finite(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], u0: torch.Tensor, plan: Shooting,
                    box: tuple[torch.Tensor, torch.Tensor] | None = None) -> bool:
    """True when every segment of ``plan``, started at ``u0 (S, n)``, stays finite under ``rhs``
    (one RK4 pass as training takes it, no gradients): a warm start that fails it is not a start."""
    with torch.no_grad():
        return bool(torch.isfinite(rk4_segments(rhs, u0, plan, box)).all())


def initial_segments(problem: Problem, ref: Reference, plan: Shooting) -> torch.Tensor:
    """Segment starts from the model as written, with measured states set to their measurements
    (an output ``g(p)·x`` divided by its factor)."""
    t = ref.batch.t
    rows = torch.searchsorted(t, plan.starts).clamp(max=t.shape[0] - 1)
    from physmend.ude.measured import factors, measured_outputs

    u = ref.states[rows, plan.exp_index].clone()  # (S, n)
    g = factors(problem.model)(ref.batch.params)  # (B, q): an output g(p)·x records x = y / g(p)
    for c, (j, i, _) in enumerate(measured_outputs(problem.model)):
        obs = ref.batch.obs[:, :, j]
        for s in range(u.shape[0]):
            b = int(plan.exp_index[s])
            col = obs[:, b]
            ok = torch.isfinite(col)
            if ok.any():
                k = int(torch.argmin((t - plan.starts[s]).abs() + (~ok) * 1e30))
                u[s, i] = col[k] / g[b, c]
    return u


def pinned_starts(batch: Batch, plan: Shooting, state_names: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which segment-start entries are the known initial state, and bounds of the trained ones.

    Returns ``pinned (S, n)``: True on an experiment's first segment, except for initial values its
    data config declares unknown (those are trained like any other segment start, within their
    range); ``lo, hi (S, n)``: that range on those entries, ``∓inf`` elsewhere.
    """
    s, n = int(plan.exp_index.shape[0]), len(state_names)
    pinned = plan.first[:, None].expand(s, n).clone()
    lo = torch.full((s, n), -math.inf, dtype=batch.u0.dtype)
    hi = torch.full((s, n), math.inf, dtype=batch.u0.dtype)
    if not any(batch.initial_ranges):
        return pinned, lo, hi
    index = {name: i for i, name in enumerate(state_names)}
    for row in torch.nonzero(plan.first).flatten().tolist():
        for name, (low, high) in batch.initial_ranges[int(plan.exp_index[row])].items():
            i = index[name]
            pinned[row, i] = False
            lo[row, i], hi[row, i] = float(low), float(high)
    return pinned, lo, hi


def output_spread(obs: torch.Tensor) -> torch.Tensor:
    """Standard deviation of each output over finite training samples ``obs (N, k)``: ``(k,)``."""
    cols = []
    for c in obs.T:
        c = c[torch.isfinite(c)]
        cols.append(c.std() if c.numel() > 1 else torch.tensor(1.0, dtype=obs.dtype))
    return torch.stack(cols).clamp_min(1e-9)


def noise_fit(batch: Batch, mask: torch.Tensor, out_std: torch.Tensor) -> float:
    """The fit term of the multiple-shooting loss that a model exact but for sensor noise would
    leave: the mean over training samples of ``(σ_bj / spread_j)²`` (``σ_bj``: noise of output j
    in experiment b, from the record's second differences; ``spread_j``: ``out_std``). NaN where no
    noise can be estimated.

    ``batch.obs (T, B, k)``, ``mask (T, B)`` (the training samples), ``out_std (k,)``."""
    from physmend.explain.residuals import noise_floor

    total, count = 0.0, 0
    t = batch.t.detach().cpu().numpy()
    for b in range(batch.obs.shape[1]):
        for j in range(batch.obs.shape[2]):
            y = batch.obs[:, b, j].detach().cpu().numpy()
            keep = mask[:, b].cpu().numpy() & np.isfinite(y)
            n = int(keep.sum())
            if n < 5:
                continue
            sigma = noise_floor(t[keep], y[keep])
            if not math.isfinite(sigma):
                continue
            total += n * (sigma / float(out_std[j])) ** 2
            count += n
    return total / count if count else float("nan")


def equation_scale(problem: Problem, spec: HybridSpec, params_seg: torch.Tensor, ref: Reference) -> tuple[torch.Tensor, torch.Tensor]:
    """``a_i`` per segment ``(S, k)`` of the corrected equations ``a_i·der(x_i) = …`` and one
    reference size ``()``: the mean RMS of ``a_i·du_i/dt`` along the model-as-written simulation."""
    model = problem.model
    if not spec.corrected:
        return torch.ones(params_seg.shape[0], 0, dtype=params_seg.dtype), torch.ones((), dtype=params_seg.dtype)
    coefs = der_coefficients(model, spec.corrected)
    idx = [model.state_names.index(n) for n in spec.corrected]
    power = ref.derivs[..., idx] * coefs(ref.batch.params)[None]
    ref_size = power.pow(2).mean(dim=(0, 1)).sqrt().mean().clamp_min(1e-30)
    return coefs(params_seg), ref_size
