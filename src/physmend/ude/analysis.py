"""What a trained hybrid model learned: trajectories, correction ranking, input sensitivities.

All analyses run along whole-trajectory simulations of the hybrid on the *training* samples
(train-role experiments before their validation split): choices made from them never look at
validation or test data. Imports ``hybrid``, ``reference``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from physmend.problem import Problem
from physmend.simulate import Batch, make_batch
from physmend.ude.hybrid import HybridModel
from physmend.ude.metrics import checkpoint_problem, hybrid_states
from physmend.ude.reference import solver_options, train_mask


@dataclass
class HybridTrajectories:
    """Training samples along the hybrid's trajectories, flattened to ``N`` rows.

    ``u (N, n_states)``, ``x (N, n_inputs)``, ``p (N, n_params)``, ``du (N, n_states)`` the
    hybrid's derivatives, ``corr (N, n_corrected)`` the network's corrections, ``z (N, n_features)``
    the normalised network inputs, ``exp (N,)`` batch index, ``t (N,)`` time (s);
    ``added (N, n_corrected)``: the correction plus what the estimates ``handed`` (those taken to
    have absorbed missing physics, :func:`absorbed`) changed in each corrected equation,
    ``f(u, x, p_estimated) − f(u, x, p_handed_back)`` (state unit / s; see :func:`handed_back`).
    """

    u: torch.Tensor
    x: torch.Tensor
    p: torch.Tensor
    du: torch.Tensor
    corr: torch.Tensor
    z: torch.Tensor
    exp: torch.Tensor
    t: torch.Tensor
    batch: Batch
    added: torch.Tensor | None = None
    handed: list[str] = field(default_factory=list)


def training_trajectories(hybrid: HybridModel, problem: Problem, cfg: Any) -> HybridTrajectories:
    """The hybrid simulated on the training and validation experiments of ``problem`` (test ones are
    never needed here, and a long test record would cost more than the rest), flattened to the
    training samples; ``exp`` indexes the experiments of ``checkpoint_problem(problem)``."""
    problem = checkpoint_problem(problem)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with torch.no_grad():
        p = hybrid.parameters_for(batch.params)
        rhs = hybrid.rhs(p)
        states = hybrid_states(hybrid, problem, batch, solver_options(cfg))
        x = batch.inputs.at(batch.t)
        mask = train_mask(problem, batch)
        pp = p[None].expand(states.shape[0], -1, -1)
        du = rhs(states, x)
        corr = hybrid.corrections(states, x, p)
        z = (hybrid.features(states, x, p) - hybrid.mean) / hybrid.std
        idx = hybrid.corrected_idx
        handed = absorbed(hybrid, problem, states[mask], x[mask], pp[mask],
                          batch.params[None].expand(states.shape[0], -1, -1)[mask], corr[mask])
        kept = handed_back(hybrid, problem, batch.params, handed)
        moved = (problem.compiled.bind(p)(states, x) - problem.compiled.bind(kept)(states, x))[..., idx]
        added = corr + moved
    tt = batch.t[:, None].expand_as(mask)
    ee = torch.arange(batch.size)[None, :].expand_as(mask)
    return HybridTrajectories(states[mask], x[mask], pp[mask], du[mask], corr[mask], z[mask], ee[mask], tt[mask], batch,
                              added[mask], handed)


ABSORBED_SHARE = 0.25
"""An estimate has absorbed part of the missing physics when it moved more than this share of its
declared range from its declared value, or when what its move changed in a corrected equation is
at least this share of the network's correction there (:func:`absorbed`)."""


def moved_far(hybrid: HybridModel, problem: Problem) -> list[str]:
    """Jointly estimated parameters whose estimate moved over :data:`ABSORBED_SHARE` of their range."""
    declared = {v.name: v for v in problem.model.parameters}
    out = []
    for name, value in hybrid.estimates().items():
        var = declared[name]
        lo, hi = var.bounds or (value, value)
        if hi > lo and abs(value - float(var.value)) > ABSORBED_SHARE * (hi - lo):
            out.append(name)
    return out


def absorbed(hybrid: HybridModel, problem: Problem, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor,
             declared: torch.Tensor, corr: torch.Tensor) -> list[str]:
    """Estimates taken to have absorbed part of the missing physics, along ``N`` training samples:
    states ``u (N, n)``, inputs ``x (N, m)``, estimated and declared parameters ``p``, ``declared
    (N, n_params)``, the network's corrections ``corr (N, n_corrected)``.

    One that moved far (:func:`moved_far`), or whose move changed some corrected equation by at
    least :data:`ABSORBED_SHARE` of the network's correction there (RMS; a conductance that grew to
    carry a radiation loss changes its equation by more than the network corrects). A smaller
    change is calibration, not missing physics: the formula is not asked to carry it (it may
    depend on states the formula does not see)."""
    out = set(moved_far(hybrid, problem))
    names = problem.compiled.parameter_names
    idx = hybrid.corrected_idx
    f = problem.compiled.bind
    with torch.no_grad():
        base = f(p)(u, x)[..., idx]
        size = corr.pow(2).nanmean(0).sqrt()  # (n_corrected,)
        for name in hybrid.estimates():
            j = names.index(name)
            back = p.clone()
            back[:, j] = declared[:, j]
            change = (base - f(back)(u, x)[..., idx]).pow(2).nanmean(0).sqrt()
            if bool((change >= ABSORBED_SHARE * size).any()):
                out.add(name)
    return [n for n in names if n in out]


def handed_back(hybrid: HybridModel, problem: Problem, params: torch.Tensor, names: list[str]) -> torch.Tensor:
    """``params (B, n_params)`` with the estimates, except ``names`` (:func:`absorbed`), which keep
    their declared values: what such an estimate changed is handed back to the corrections — to the
    symbolic target and to the recorded mismatch the formulas are judged against. (The proposed
    model is the model as written plus the formulas: a formula fitted on top of an estimate that
    carried part of the missing term would miss exactly that part.)"""
    p = hybrid.parameters_for(params).detach().clone()
    for name in names:
        j = problem.compiled.parameter_names.index(name)
        p[:, j] = params[:, j]
    return p


def rank_corrections(hybrid: HybridModel, traj: HybridTrajectories) -> list[tuple[str, float]]:
    """The seed paper's heuristic ``mean_t |ΔNN_i| / max_t |du_i/dt|``, largest first.

    Means and maxima are taken per experiment and averaged, so long records do not dominate.
    """
    idx = hybrid.corrected_idx
    scores = torch.zeros(len(idx), dtype=traj.corr.dtype)
    exps = traj.exp.unique()
    for e in exps:
        m = traj.exp == e
        mean_corr = traj.corr[m].abs().mean(0)
        max_du = traj.du[m][:, idx].abs().amax(0).clamp_min(1e-300)
        scores += mean_corr / max_du
    scores /= max(len(exps), 1)
    order = torch.argsort(scores, descending=True).tolist()
    return [(hybrid.spec.corrected[i], float(scores[i])) for i in order]


def input_jacobian(hybrid: HybridModel, traj: HybridTrajectories, *, max_rows: int = 4000) -> torch.Tensor:
    """``J[r, i, j] = d corr_i / d z_j`` along the trajectories: ``(R, n_corrected, n_features)``.

    ``z`` are the normalised inputs, so each column is already scaled by its input's spread
    (``d corr / d input · std(input)``). At most ``max_rows`` evenly spaced rows are used.
    """
    z = traj.z
    if z.shape[0] > max_rows:
        z = z[torch.linspace(0, z.shape[0] - 1, max_rows).long()]
    with torch.no_grad():
        jac = torch.func.vmap(torch.func.jacrev(hybrid.corrections_of_z))(z)
    return jac


def rank_inputs(hybrid: HybridModel, jac: torch.Tensor, keep: list[str] | None = None) -> list[tuple[str, float]]:
    """Inputs ranked by mean |J| over samples and the kept outputs (each output normalised to max 1)."""
    rows = [hybrid.spec.corrected.index(k) for k in keep] if keep else list(range(jac.shape[1]))
    mag = jac[:, rows].abs().mean(0)  # (n_kept, n_features)
    mag = mag / mag.amax(-1, keepdim=True).clamp_min(1e-300)
    score = mag.mean(0)
    order = torch.argsort(score, descending=True).tolist()
    names = hybrid.spec.input_names
    return [(names[i], float(score[i])) for i in order]


def equation_corrections(hybrid: HybridModel, problem: Problem, traj: HybridTrajectories, kept: list[str]) -> torch.Tensor:
    """``a_i · added_i`` of each kept equation ``a_i·der(x_i) = …`` along the samples: ``(N, k)``.

    ``added`` is the network's correction plus what jointly estimated parameters that moved far
    from their declared values changed in that equation (:class:`HybridTrajectories`): a parameter
    that drifted to absorb part of the missing physics hands it back, and the formula is fitted to
    the mismatch of the model it will be attached to. In the equation's own units (W for a heat
    balance), so a term that is the same physical flow in experiments of different size (capacity)
    is the same function of its inputs.
    """
    from physmend.modeling.compile import lambdify_torch

    model = problem.model
    psyms = [v.symbol for v in model.parameters]
    cols = []
    values = traj.corr if traj.added is None else traj.added
    for name in kept:
        coef = lambdify_torch(psyms, [model.der_coefficient[name]], "der coefficient")(*traj.p.unbind(-1))[0]
        coef = torch.as_tensor(coef, dtype=traj.p.dtype).expand(traj.p.shape[0])
        cols.append(coef * values[:, hybrid.spec.corrected.index(name)])
    return torch.stack(cols, 1)


@dataclass
class InputGroup:
    """Network inputs that move together along every training trajectory (|r| ≥ a threshold).

    ``representative`` stands for the group (a measured quantity where the group has one),
    ``members`` are all its inputs (representative first) and ``signs`` their correlation signs.
    """

    representative: str
    members: list[str]
    signs: list[float]


def group_inputs(hybrid: HybridModel, traj: HybridTrajectories, measured: list[str], threshold: float,
                 order: list[str]) -> list[InputGroup]:
    """Group inputs the training data cannot tell apart: each group's members correlate with its
    representative at ``|r| >= threshold`` (no chaining). Measured quantities claim members first
    (their values are known, a hidden state's are simulated), then the other inputs in ``order``.
    """
    names = hybrid.spec.input_names
    z = traj.z
    zc = z - z.mean(0)
    norm = zc.pow(2).sum(0).sqrt()
    ok = norm > 1e-12
    corr = (zc.T @ zc) / (norm[:, None] * norm[None, :]).clamp_min(1e-300)
    free = set(names)
    groups: list[InputGroup] = []
    for rep in [n for n in measured if n in names] + [n for n in order if n not in measured]:
        if rep not in free:
            continue
        i = names.index(rep)
        members, signs = [rep], [1.0]
        free.discard(rep)
        if bool(ok[i]):
            for j, other in enumerate(names):
                if other in free and bool(ok[j]) and abs(float(corr[i, j])) >= threshold:
                    members.append(other)
                    signs.append(1.0 if float(corr[i, j]) > 0 else -1.0)
                    free.discard(other)
        groups.append(InputGroup(rep, members, signs))
    return groups


def rank_groups(hybrid: HybridModel, jac: torch.Tensor, groups: list[InputGroup], keep: list[str] | None = None
                ) -> list[tuple[InputGroup, float]]:
    """Groups ranked by the sensitivity along their common direction, largest first.

    Moving every member of a group together (each by its spread, with its sign) changes a
    correction by ``Σ_j s_j J_j``: how the network splits a dependence among look-alike inputs
    does not matter. Per output normalised to max 1, then averaged over the kept outputs.
    """
    names = hybrid.spec.input_names
    rows = [hybrid.spec.corrected.index(k) for k in keep] if keep else list(range(jac.shape[1]))
    j = jac[:, rows]  # (R, k, n_features)
    cols = []
    for g in groups:
        idx = [names.index(m) for m in g.members]
        signs = torch.tensor(g.signs, dtype=j.dtype)
        cols.append((j[..., idx] * signs).sum(-1).abs().mean(0))  # (k,)
    mag = torch.stack(cols, -1)  # (k, n_groups)
    mag = mag / mag.amax(-1, keepdim=True).clamp_min(1e-300)
    score = mag.mean(0)
    order = torch.argsort(score, descending=True).tolist()
    return [(groups[i], float(score[i])) for i in order]
