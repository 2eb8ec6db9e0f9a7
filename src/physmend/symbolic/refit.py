"""Re-fitting a formula's constants through the simulator (multiple shooting, Levenberg–Marquardt).

The loss is the one :func:`physmend.ude.train.train` minimises for a hybrid without a network:
all training segments (``train.segment_length``) solved at once by fixed-step RK4
(``train.step``), the mean squared error of the measured outputs (each scaled by its spread)
plus ``train.continuity_weight`` × the mean squared gap between a segment's end and the next
segment's start (in units of each state's spread). The unknowns are the few constants and the
starts of every segment but each experiment's first (which starts from its known initial state,
except for initial values the data config declares unknown: unknowns within their range).

That loss is a sum of squares, and its unknowns couple only segment by segment, so
Levenberg–Marquardt solves it in a handful of iterations where a first-order method (Adam) needs
hundreds of epochs and still stops short of the minimum. Its Jacobian costs one batched solve:
a segment depends only on its own start and on the constants, so perturbing state ``i`` of every
segment's start at once gives every segment's sensitivity to its own start ``i`` (forward
differences; ``n_states + n_constants`` perturbed copies of the segments solved side by side).
The normal equations are sparse (block-banded in the segment starts) and solved as such.

Everything here needs torch and the simulator; it is imported only by the symbolic stage.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import torch

from physmend.settings import TrainSettings
from physmend.symbolic._errors import SymbolicError

#: tensors of at most this many elements per batched solve of perturbed copies (memory guard).
MAX_ELEMENTS = 30_000_000


def constant_bounds(value: float) -> tuple[float, float]:
    """Where a formula's constant may move in the re-fit: anywhere (``(-inf, inf)``). A discovered
    term's constants have no physically declared bounds, and a box around the regression's value
    (it was ×/÷20) would only hide a regression that sized the term wrong; the Levenberg–Marquardt
    steps are safe without one (a step whose segments leave the finite range is refused), and the
    standard error says when the data cannot pin a constant down. ``value`` is unused."""
    return -math.inf, math.inf


@dataclass
class RefitResult:
    """Outcome of :func:`refit_constants`.

    Attributes:
        constants: parameter name -> re-fitted value (the regression's value where nothing improved).
        loss_before: multiple-shooting loss at the regression's constants (dimensionless).
        loss_after: the same loss at ``constants``.
        iterations: accepted Levenberg–Marquardt steps.
        converged: True when the relative loss decrease fell below the tolerance (or no step
            could lower the loss any more); False when ``max_iterations`` ran out first.
        stderr: parameter name -> standard error of the re-fitted value, in its own units, from
            the Levenberg–Marquardt Jacobian at the end (``s²·(JᵀJ)⁻¹`` with ``s²`` the loss per
            degree of freedom; the segment starts are unknowns too); ``inf`` where the data cannot
            pin the constant down (a singular or indefinite ``JᵀJ``). Empty when nothing was fitted.
    """

    constants: dict[str, float]
    loss_before: float
    loss_after: float
    iterations: int
    converged: bool
    stderr: dict[str, float] = field(default_factory=dict)

    def pinned(self, name: str, share: float = 0.5) -> bool:
        """Whether the data pin constant ``name`` down: its standard error is below ``share`` of its size."""
        se = self.stderr.get(name, math.inf)
        return math.isfinite(se) and se < share * abs(self.constants.get(name, 0.0))


class _Shooting:
    """The multiple-shooting residuals of a corrected model and their Jacobian.

    Unknowns ``x = (θ (K,), v (F, n))``: the constants in their own units and the free segment
    starts as offsets from their initial guesses, in units of each state's spread.
    """

    def __init__(self, problem: Any, cfg: Any, ref: Any, names: Sequence[str], starts: torch.Tensor | None = None) -> None:
        from physmend.ude.hybrid import HybridModel, HybridSpec
        from physmend.ude.reference import train_mask
        from physmend.ude.shooting import initial_segments, output_spread, pinned_starts, plan_shooting
        from physmend.ude.warmstart import forced_trajectories, segment_starts

        compiled = problem.compiled
        unknown = [n for n in names if n not in compiled.parameter_names]
        if unknown:
            raise SymbolicError(f"refit: {unknown} are not parameters of model {problem.model.name!r}")
        self.problem = problem
        self.names = list(names)
        self.idx = [compiled.parameter_names.index(n) for n in names]
        self.plan = plan = plan_shooting(problem, ref.batch, cfg)
        seg0 = initial_segments(problem, ref, plan) if starts is None else starts.clone()
        if starts is None and TrainSettings.build(cfg.train).warm_start != "none":  # as training: from the forced records
            spec = HybridSpec(corrected=[], in_states=compiled.state_names[:1], in_observed=[], in_inputs=[],
                              in_parameters=[], widths=[], activation="tanh", mean=[0.0], std=[1.0], out_scale=[])
            forced = forced_trajectories(problem, ref.batch, HybridModel(compiled, spec, problem.dtype), plan.dt)
            if forced is not None:
                seg0 = segment_starts(forced, plan.exp_index, plan.starts, seg0)
        mask = train_mask(problem, ref.batch)
        self.seg0 = seg0
        self.fixed_first = ref.batch.u0[plan.exp_index]
        self.scale = ref.states[mask].std(0).clamp_min(1e-3)  # (n,)
        self.out_std = output_spread(ref.batch.obs[mask])
        self.params = ref.batch.params[plan.exp_index]  # (S, n_params)
        self.S, self.n = seg0.shape
        self.K = len(self.idx)
        # (S, n) entries that are an experiment's known initial state; an initial value its data
        # config declares unknown is an unknown here too, within its range (as training treats it)
        self.pinned, self.start_lo, self.start_hi = pinned_starts(ref.batch, plan, compiled.state_names)
        self.free = (~self.pinned.all(-1)).nonzero().squeeze(-1)  # (F,) segments with unknown starts
        self.F = int(self.free.numel())
        self.col_of = torch.full((self.S,), -1, dtype=torch.long)
        self.col_of[self.free] = torch.arange(self.F)
        self.has_next = plan.next_of >= 0
        self.gaps = self.has_next.nonzero().squeeze(-1)  # (G,) segments followed by another
        self.N = int(plan.obs_y.numel())
        G = int(self.gaps.numel())
        self.w_fit = 1.0 / math.sqrt(max(self.N, 1))
        self.w_gap = math.sqrt(TrainSettings.build(cfg.train).continuity_weight / max(G * self.n, 1))
        self.n_res = self.N + G * self.n
        self.n_unknowns = self.K + self.F * self.n
        declared = {v.name: v.bounds for v in problem.model.parameters if v.uncertain and v.bounds is not None}
        bounds = [tuple(map(float, declared[n])) if n in declared else constant_bounds(v)
                  for n, v in zip(self.names, self.params[0, self.idx].tolist())]
        self.lo = torch.tensor([b[0] for b in bounds], dtype=seg0.dtype)
        self.hi = torch.tensor([b[1] for b in bounds], dtype=seg0.dtype)
        eps = torch.finfo(seg0.dtype).eps
        self.h = 8.0 * math.sqrt(eps)  # relative forward-difference step

    # -- solving ------------------------------------------------------------------------------------
    def offset_bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(lo, hi)``, each ``(F, n)``: the offsets ``v`` of the free segments whose starts stay within
        their declared range (``∓inf`` where none is declared)."""
        lo = (self.start_lo - self.seg0) / self.scale
        hi = (self.start_hi - self.seg0) / self.scale
        return lo[self.free], hi[self.free]

    def starts(self, v: torch.Tensor) -> torch.Tensor:
        """Segment starts ``(S, n)`` for offsets ``v (S, n)`` (first segments: the known initial state;
        a declared-unknown initial value within its range)."""
        return torch.where(self.pinned, self.fixed_first, torch.clamp(self.seg0 + v * self.scale, self.start_lo, self.start_hi))

    def _solve(self, u0: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """RK4 over ``C`` stacked copies of the segments: ``u0, p (C·S, ·)`` -> states ``(K+1, C·S, n)``
        and outputs ``(K+1, C·S, k)`` on the grid."""
        from physmend.ude.shooting import rk4_segments

        copies = u0.shape[0] // self.S
        plan = self.plan if copies == 1 else dataclasses.replace(self.plan, x_half=self.plan.x_half.repeat(1, copies, 1))
        with torch.no_grad():
            traj = rk4_segments(self.problem.compiled.bind(p), u0, plan)
            y = self.problem.compiled.outputs(traj, plan.x_half[0::2], p[None])
        return traj, y

    def with_constants(self, theta: torch.Tensor) -> torch.Tensor:
        p = self.params.clone()
        p[:, self.idx] = theta.to(p.dtype)
        return p

    def residuals(self, theta: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Residuals ``(R,)`` (their squared sum is the loss) and the solve ``(u0, states, outputs)``."""
        u0 = self.starts(v)
        traj, y = self._solve(u0, self.with_constants(theta))
        return self._residuals_of(u0, traj, y), (u0, traj, y)

    def _residuals_of(self, u0: torch.Tensor, traj: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        plan = self.plan
        ya = y[plan.obs_k, plan.obs_s, plan.obs_j]
        yb = y[plan.obs_k + 1, plan.obs_s, plan.obs_j]
        fit = (ya + plan.obs_w * (yb - ya) - plan.obs_y) / self.out_std[plan.obs_j] * self.w_fit
        gap = (traj[-1][self.gaps] - u0[plan.next_of[self.gaps]]) / self.scale * self.w_gap
        return torch.cat([fit, gap.reshape(-1)])

    # -- Jacobian -----------------------------------------------------------------------------------
    def jacobian(self, theta: torch.Tensor, v: torch.Tensor, base: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> sps.csr_matrix:
        """Sparse ``(R, K + F·n)`` Jacobian of :meth:`residuals` at ``(θ, v)`` (forward differences);
        ``base`` is the solve there."""
        u0, traj0, y0 = base
        r0 = self._residuals_of(u0, traj0, y0)
        p0 = self.with_constants(theta)
        # relative steps (a constant of 0: an absolute one)
        step_t = self.h * torch.where(theta != 0, theta.abs(), torch.ones_like(theta))
        # directions: state i of every start (n), then constant k (K)
        dirs = list(range(self.n + self.K))
        per_copy = traj0.shape[0] * self.S * max(self.n, y0.shape[-1])
        chunk = max(1, MAX_ELEMENTS // max(per_copy, 1))
        d_end = torch.empty(self.n, self.S, self.n, dtype=traj0.dtype)  # d end(s) / d v(s, i)
        d_y = torch.empty(y0.shape[0], self.n, self.S, y0.shape[-1], dtype=y0.dtype)  # d y(s) / d v(s, i)
        d_theta = torch.empty(r0.numel(), self.K, dtype=r0.dtype)
        for lo in range(0, len(dirs), chunk):
            part = dirs[lo:lo + chunk]
            us, ps = [], []
            for d in part:
                u, p = u0.clone(), p0
                if d < self.n:
                    u[:, d] += self.h * self.scale[d]
                else:
                    p = p0.clone()
                    p[:, self.idx[d - self.n]] += step_t[d - self.n]
                us.append(u)
                ps.append(p)
            traj, y = self._solve(torch.cat(us), torch.cat(ps))
            for c, d in enumerate(part):
                tc, yc = traj[:, c * self.S:(c + 1) * self.S], y[:, c * self.S:(c + 1) * self.S]
                if d < self.n:
                    d_end[d] = (tc[-1] - traj0[-1]) / self.h
                    d_y[:, d] = (yc - y0) / self.h
                else:
                    k = d - self.n
                    d_theta[:, k] = (self._residuals_of(u0, tc, yc) - r0) / step_t[k]
        rows, cols, vals = [], [], []
        # constants: dense columns
        rows.append(np.repeat(np.arange(r0.numel()), self.K))
        cols.append(np.tile(np.arange(self.K), r0.numel()))
        vals.append(d_theta.numpy().ravel())
        # fit rows: the starts of their own segment
        plan = self.plan
        col = self.col_of[plan.obs_s]
        ok = (col >= 0).numpy()
        scale = (self.w_fit / self.out_std[plan.obs_j])
        wa, wb = (1 - plan.obs_w) * scale, plan.obs_w * scale
        dfit = wa[None] * d_y[plan.obs_k, :, plan.obs_s, plan.obs_j].T + wb[None] * d_y[plan.obs_k + 1, :, plan.obs_s, plan.obs_j].T
        obs_rows = np.arange(self.N)[ok]
        for i in range(self.n):
            rows.append(obs_rows)
            cols.append(self.K + col.numpy()[ok] * self.n + i)
            vals.append(dfit[i].numpy()[ok])
        # gap rows: the start of their own segment (through its end) and the next segment's start
        n = self.n
        for g, s in enumerate(self.gaps.tolist()):
            base_row = self.N + g * n
            if int(self.col_of[s]) >= 0:
                block = (d_end[:, s, :] / self.scale[None, :] * self.w_gap).T.numpy()  # (l, i)
                rr, ii = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
                rows.append(base_row + rr.ravel())
                cols.append(self.K + int(self.col_of[s]) * n + ii.ravel())
                vals.append(block.ravel())
            nxt = int(plan.next_of[s])
            rows.append(base_row + np.arange(n))
            cols.append(self.K + int(self.col_of[nxt]) * n + np.arange(n))
            vals.append(np.full(n, -self.w_gap))
        return sps.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(r0.numel(), self.n_unknowns))


def segment_guesses(problem: Any, cfg: Any, ref: Any, guide: Any = None) -> torch.Tensor:
    """Initial guesses of the segment starts ``(S, n)`` of :func:`refit_constants` on ``problem`` — to
    be shared, through ``starts``, by re-fits of models that differ only in a correction (the same
    records, so the same segments).

    Without ``guide``: the guesses :func:`refit_constants` makes for ``problem`` itself. With
    ``guide``, a trained hybrid model of ``problem`` (the network the formulas stand for): its forced
    records — measured states on their smoothed records, the hidden ones simulated with the network's
    correction — or, where no output measures a state, its whole-trajectory simulation. A hidden state
    of the model as written drifts by the missing term; the network's does not, so every candidate
    formula starts its re-fit near the states it would reach, and a few steps compare forms rather
    than how far each must first move its starts."""
    shoot = _Shooting(problem, cfg, ref, [])
    if guide is None:
        return shoot.seg0
    from physmend.ude.metrics import hybrid_states
    from physmend.ude.outcome import TrainingDiverged
    from physmend.ude.reference import solver_options
    from physmend.ude.shooting import initial_segments
    from physmend.ude.warmstart import forced_trajectories, segment_starts

    plan = shoot.plan
    with torch.no_grad():
        forced = forced_trajectories(problem, ref.batch, guide, plan.dt)
        if forced is not None:
            return segment_starts(forced, plan.exp_index, plan.starts, shoot.seg0)
        try:
            states = hybrid_states(guide, problem, ref.batch, solver_options(cfg))
        except TrainingDiverged:
            return shoot.seg0
    if not bool(torch.isfinite(states).all()):
        return shoot.seg0
    return initial_segments(problem, dataclasses.replace(ref, states=states), plan)


def refit_constants(problem: Any, cfg: Any, ref: Any, names: Sequence[str], *, max_iterations: int = 50,
                    rtol: float = 1e-6, uncertainty: bool = True, starts: torch.Tensor | None = None) -> RefitResult:
    """Re-fit the model parameters ``names`` (a formula's constants) by multiple shooting.

    Args:
        problem: the corrected model and its experiments (``physmend.problem.Problem``); the
            constants are parameters of ``problem.compiled``, starting from their values there.
        cfg: configuration with ``train.step``, ``train.segment_length``, ``train.continuity_weight``
            and ``train.warm_start`` (as training uses them).
        ref: the whole-trajectory simulation of ``problem`` (:func:`physmend.ude.reference.reference`).
        names: parameter names of the constants (unbounded: :func:`constant_bounds`).
        max_iterations: at most this many accepted Levenberg–Marquardt steps.
        rtol: stop when a step lowers the loss by less than this fraction.
        uncertainty: compute the constants' standard errors (one more Jacobian) — not needed
            where only the loss is compared.
        starts: initial guesses of the segment starts ``(S, n)`` (:func:`segment_guesses`); default:
            this model's own (its forced records where a warm start applies: one fixed-step solve).

    Returns:
        The constants and the loss before and after; where the loss cannot be evaluated (the
        fixed-step solve leaves the finite range) the constants are returned unchanged.
    """
    shoot = _Shooting(problem, cfg, ref, names, starts)
    theta = shoot.params[0, shoot.idx].clone()
    start = dict(zip(shoot.names, theta.tolist()))
    v = torch.zeros_like(shoot.seg0)
    r, solved = shoot.residuals(theta, v)
    loss = float(r @ r)
    if not math.isfinite(loss) or not shoot.names:  # nothing to fit, or the fixed-step solve fails already
        return RefitResult(start, loss, loss, 0, bool(math.isfinite(loss)))
    before, lam, it, converged = loss, 1e-3, 0, False
    free = shoot.free
    v_lo, v_hi = shoot.offset_bounds()
    while it < max_iterations:
        J = shoot.jacobian(theta, v, solved)
        rn = r.numpy()
        A, g = _held(shoot, v, (v_lo, v_hi), (J.T @ J).tocsc(), J.T @ rn)
        D = sps.diags(np.maximum(A.diagonal(), 1e-12))
        accepted = False
        while lam < 1e10:
            step = torch.from_numpy(spla.spsolve((A + lam * D).tocsc(), -g)).to(theta.dtype)
            t_new = torch.minimum(torch.maximum(theta + step[:shoot.K], shoot.lo), shoot.hi)
            v_new = v.clone()
            v_new[free] = torch.minimum(torch.maximum(v[free] + step[shoot.K:].reshape(shoot.F, shoot.n), v_lo), v_hi)
            r_new, solved_new = shoot.residuals(t_new, v_new)
            l_new = float(r_new @ r_new)
            if math.isfinite(l_new) and l_new < loss:
                accepted = True
                lam = max(lam / 3, 1e-12)
                break
            lam *= 4
        if not accepted:  # no step lowers the loss: a (local) minimum
            converged = True
            break
        it += 1
        gain = (loss - l_new) / loss
        theta, v, r, solved, loss = t_new, v_new, r_new, solved_new, l_new
        if gain < rtol:
            converged = True
            break
    stderr = _standard_errors(shoot, theta, v, solved, loss) if uncertainty else {}
    return RefitResult(dict(zip(shoot.names, theta.tolist())), before, loss, it, converged, stderr)


def _held(shoot: _Shooting, v: torch.Tensor, bounds: tuple[torch.Tensor, torch.Tensor], A: Any,
          g: np.ndarray) -> tuple[Any, np.ndarray]:
    """The normal equations ``A = JᵀJ``, ``g = Jᵀr`` with the offsets that cannot move this step held
    (no gradient, a step of zero: :func:`_without`): an experiment's known initial value in a segment
    that has an unknown one (its column is the start's effect on the trajectory, but the start is not
    an unknown), and a start at a bound of its declared range (``bounds``, :meth:`_Shooting.offset_bounds`)
    whose gradient points out of it. Left in, they predict gains the clamped step never makes, and the
    damping grows until every step crawls."""
    K = shoot.K
    vf = v[shoot.free].reshape(-1).numpy()
    lo, hi = (b.reshape(-1).numpy() for b in bounds)
    held = shoot.pinned[shoot.free].reshape(-1).numpy() | ((vf <= lo) & (g[K:] > 0)) | ((vf >= hi) & (g[K:] < 0))
    if not held.any():
        return A, g
    hold = np.concatenate([np.zeros(K, dtype=bool), held])
    return _without(A, hold), np.where(hold, 0.0, g)


def _without(A: Any, hold: np.ndarray) -> Any:
    """``A`` (sparse, unknowns × unknowns) with the rows and columns where ``hold`` is True replaced by
    those of the identity: those unknowns out of the linear system, which stays solvable."""
    keep = sps.diags((~hold).astype(float))
    return (keep @ A @ keep + sps.diags(hold.astype(float))).tocsc()


def _standard_errors(shoot: _Shooting, theta: torch.Tensor, v: torch.Tensor, solved: Any, loss: float) -> dict[str, float]:
    """Standard errors of the constants: ``sqrt(s²·[(JᵀJ)⁻¹]_kk)`` at ``(θ, v)`` (see :class:`RefitResult`)."""
    import warnings

    J = shoot.jacobian(theta, v, solved)
    rows, unknowns = J.shape
    s2 = loss / max(rows - unknowns, 1)
    # a known initial value is not an unknown (see _held)
    pinned = np.concatenate([np.zeros(shoot.K, dtype=bool), shoot.pinned[shoot.free].reshape(-1).numpy()])
    rhs = np.zeros((unknowns, shoot.K))
    rhs[np.arange(shoot.K), np.arange(shoot.K)] = 1.0
    with warnings.catch_warnings():  # a singular JᵀJ: the constant is not pinned down (inf below)
        warnings.simplefilter("ignore")
        try:
            cols = np.asarray(spla.spsolve(_without(J.T @ J, pinned), rhs)).reshape(unknowns, shoot.K)
            var = np.diag(cols[:shoot.K]) * s2
        except (RuntimeError, ValueError):
            var = np.full(shoot.K, np.nan)
    return {name: float(np.sqrt(x)) if np.isfinite(x) and x >= 0 else math.inf for name, x in zip(shoot.names, var)}
