"""The stack: M hybrid models trained as one batched multiple-shooting solve — losses, the batched
AdamW step with per-model clipping, the batched warm start, chained starts; its checkpoint
evaluations come from :class:`~physmend.ude.stack.evaluation.StackEvaluation`, its drive-form solves
from :class:`~physmend.ude.stack.drives.StackDrives`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
import dataclasses

import torch

from physmend.problem import Problem
from physmend.settings import TrainingSettings
from physmend.ude.checkpoints import Checkpoints
from physmend.simulate import make_batch
from physmend.ude.hybrid import ACTIVATIONS, HybridModel, HybridSpec
from physmend.ude.stack.net import StackedNet, pad_networks
from physmend.ude.stack.drives import StackDrives
from physmend.ude.stack.evaluation import StackEvaluation
from physmend.ude.stack.plan import plan_key, time_grid_parts
from physmend.ude.metrics import checkpoint_problem
from physmend.ude.reference import Reference, train_mask
from physmend.ude.shooting import Shooting, equation_scale, output_spread, chained_starts, pinned_starts, rk4_segments, BOX_MARGIN
from physmend.ude.warmstart import Forced, fit_models, recall_derived, remember_derived, same_warm_start


@dataclass
class Member:
    """One trial of the stack: everything that is its own outside the stacked tensors."""

    slot: int  # index into cfgs (and the result list)
    cfg: TrainingSettings  # its settings, times resolved
    hybrid: HybridModel
    forced: Forced | None
    seg0: torch.Tensor  # (S, n)
    lrs: list[float]  # learning rate of epochs 1..E (as train()'s scheduler gives them)
    marks: Checkpoints  # its checkpoints: history, best, patience, cycle (shared with train())
    outcome: BaseException | None = None  # set when the model stops with an error
    done: bool = False
    warm_key: str | None = None  # its stored warm start (:func:`physmend.ude.warmstart.warm_key`), if batched


class Stack(StackDrives, StackEvaluation):
    """The active models' stacked trainable tensors, their AdamW state, and the batched solves."""

    BETAS = (0.9, 0.999)
    EPS = 1e-8
    MAX_NORM = 10.0

    def __init__(self, members: list[Member], problem: Problem, ref: Reference, plan: Shooting, cfg: TrainingSettings) -> None:
        order = list(ACTIVATIONS)  # models of one activation side by side (see StackedNet)
        members = sorted(members, key=lambda mem: order.index(mem.hybrid.spec.activation))
        self.members = members
        self.problem = problem
        self.ref = ref
        self.plan = plan
        self.template = members[0].hybrid  # index lists, normalisation: the same for every model
        dtype = problem.dtype
        self.dtype = dtype
        self.net, masks = pad_networks([m.hybrid for m in members], dtype)
        self.spec: HybridSpec = self.template.spec
        self.est_idx = self.template.est_idx
        self.seg0 = torch.stack([m.seg0 for m in members])  # (M, S, n)
        # (tensor, gradient mask, weight decay?, clipped?): the network and the estimates in the order of
        # hybrid.parameters() (clipped together, as train() clips them), then the segment offsets
        net_params = [x for pair in zip(self.net.weights, self.net.biases) for x in pair]
        self.params: list[tuple[torch.Tensor, torch.Tensor | None, bool, bool]] = [(p, mk, True, True) for p, mk in zip(net_params, masks)]
        if self.est_idx:
            self.params.append((torch.stack([m.hybrid.est_raw.detach() for m in members]), None, False, True))
        self.params.append((torch.zeros(len(members), *members[0].seg0.shape, dtype=dtype), None, False, False))
        tensors = [p.detach().clone().requires_grad_(True) for p, *_ in self.params]
        self.params = [(t, mk, decay, clip) for t, (_, mk, decay, clip) in zip(tensors, self.params)]
        self._bind_tensors(tensors)
        self.exp_avg = [torch.zeros_like(p) for p, *_ in self.params]
        self.exp_avg_sq = [torch.zeros_like(p) for p, *_ in self.params]
        self.step_count = 0
        self.weight_decay = torch.tensor([float(m.cfg.train.weight_decay) for m in members], dtype=dtype)
        self.sparsity = torch.tensor([m.cfg.train.sparsity for m in members], dtype=dtype)
        self.mean = self.template.mean
        self.std = self.template.std
        # shared pieces of the training solve (as in train())
        tm = train_mask(problem, ref.batch)
        self.fixed_first = ref.batch.u0[plan.exp_index]
        self.pinned, self.lo, self.hi = pinned_starts(ref.batch, plan, problem.compiled.state_names)
        self.state_scale = ref.states[tm].std(0).clamp_min(1e-3)
        self.box = members[0].hybrid.spec.box(BOX_MARGIN, problem.dtype)  # one reference: one range for all
        self.initial_estimates: dict[tuple[str, ...], torch.Tensor] = {}  # as HybridModel.initial_estimates
        self.out_std = output_spread(ref.batch.obs[tm])
        self.params_seg = ref.batch.params[plan.exp_index]
        self.has_next = plan.next_of >= 0
        self.cont_w = float(cfg.train.continuity_weight)
        self.eq_coef, self.eq_ref = (equation_scale(problem, self.spec, self.params_seg, ref)
                                     if bool((self.sparsity > 0).any()) and self.spec.corrected else (None, None))
        self.checked = checkpoint_problem(problem)  # checkpoints simulate train/validation experiments only
        self.eval_batch = make_batch(self.checked.experiments, problem.compiled, dtype)
        self.full_batch = self.eval_batch if self.checked is problem else make_batch(problem.experiments, problem.compiled, dtype)
        self.parts = time_grid_parts(self.checked, self.eval_batch)
        self._rows_changed()

    # -- bookkeeping ----------------------------------------------------------------------------------
    @property
    def size(self) -> int:
        return len(self.members)

    def _rows_changed(self) -> None:
        m = self.size
        self.plan_rows = dataclasses.replace(self.plan, x_half=self.plan.x_half.repeat(1, m, 1))  # rows model-major

    def keep(self, positions: list[int]) -> None:
        """Keep only the models at stack positions ``positions`` (the others have stopped)."""
        if positions == list(range(self.size)):
            return
        rows = torch.tensor(positions, dtype=torch.long)
        tensors = [p.detach()[rows].clone().requires_grad_(True) for p, *_ in self.params]
        self.params = [(t, None if mk is None else mk[rows], decay, clip)
                       for t, (_, mk, decay, clip) in zip(tensors, self.params)]
        self._bind_tensors(tensors)
        self.net.use = [None if u is None else u[rows] for u in self.net.use]
        self.net.activations = [self.net.activations[i] for i in positions]
        self.net.__post_init__()
        self.net.scale = self.net.scale[rows]
        self.exp_avg = [t[rows].clone() for t in self.exp_avg]
        self.exp_avg_sq = [t[rows].clone() for t in self.exp_avg_sq]
        self.seg0 = self.seg0[rows]
        self.weight_decay = self.weight_decay[rows]
        self.sparsity = self.sparsity[rows]
        self.members = [self.members[i] for i in positions]
        self._rows_changed()

    def _bind_tensors(self, tensors: list[torch.Tensor]) -> None:
        """Point the network, estimates and segment offsets at ``tensors`` (in the order of ``params``)."""
        n_net = 2 * len(self.net.weights)
        self.net.weights = tensors[0:n_net:2]
        self.net.biases = tensors[1:n_net:2]
        self.est_raw = tensors[n_net] if self.est_idx else None
        self.free = tensors[-1]

    # -- the hybrid right-hand side over stacked rows ------------------------------------------------
    def _parameters_for(self, p: torch.Tensor, est_raw: torch.Tensor | None, m: int) -> torch.Tensor:
        """``p (R, n_params)`` repeated for ``m`` models ``(m·R, n_params)`` with each model's estimates."""
        rows = p.shape[0]
        p = p[None].expand(m, rows, p.shape[-1]).clone()
        if est_raw is not None:
            h = self.template
            values = h.est_lo + (h.est_hi - h.est_lo) * torch.sigmoid(est_raw)  # (m, n_est)
            p[:, :, self.est_idx] = values[:, None, :].to(p.dtype)
        return p.reshape(m * rows, -1)

    def _coef(self, p: torch.Tensor) -> torch.Tensor | None:
        """The corrected equations' ``a_i(p)`` ``(rows, k)`` (None when the network gives rates)."""
        return None if self.template.coefficients is None else self.template.equation_coefficients(p)

    def _corrections(self, net: StackedNet, m: int, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor,
                     coef: torch.Tensor | None) -> torch.Tensor:
        """Corrections ``(..., m·R, k)`` of ``u (..., m·R, n)``: each model's rows through its own
        network; ``coef (m·R, k)``: the equations' ``a_i(p)`` (None: rates, nothing to divide by)."""
        z = (self.template.features(u, x, p) - self.mean) / self.std
        *lead, rows, n_feat = z.shape
        r = rows // m
        if not lead:
            out = net(z.reshape(m, r, n_feat)).reshape(rows, -1)
            return out if coef is None else out / coef
        zz = z.reshape(*lead, m, r, n_feat).movedim(-3, 0).reshape(m, -1, n_feat)
        out = net(zz).reshape(m, *lead, r, -1).movedim(0, -3).reshape(*lead, rows, -1)
        return out if coef is None else out / coef

    def _rhs(self, net: StackedNet, m: int, p: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``f(u, x) -> du/dt`` over stacked rows, structured as :meth:`HybridModel.rhs`."""
        physics = self.problem.compiled.bind(p)
        idx = self.template.corrected_idx
        n = len(self.problem.compiled.state_names)
        if not idx:
            return physics
        coef = self._coef(p)  # once per solve, not once per evaluation
        if len(idx) == n and idx == list(range(n)):
            return lambda u, x: physics(u, x) + self._corrections(net, m, u, x, p, coef)
        index = torch.tensor(idx, dtype=torch.long)

        def f(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            corr = self._corrections(net, m, u, x, p, coef)
            du = physics(u, x)
            if du.shape[:-1] != corr.shape[:-1]:
                lead = torch.broadcast_shapes(du.shape[:-1], corr.shape[:-1])
                du, corr = du.expand(*lead, n), corr.expand(*lead, corr.shape[-1])
            return du.index_add(-1, index, corr)

        return f

    # -- one epoch -----------------------------------------------------------------------------------------
    def losses(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each model's training loss and fit loss ``(M,)``, as train() computes them for one."""
        m, plan = self.size, self.plan_rows
        s, n = self.seg0.shape[1:]
        shared = None
        if self.problem.compiled.shares_matrices(m * int(torch.unique(self.plan.exp_index).numel())):
            p_exp = self._parameters_for(self.ref.batch.params, self.est_raw, m)  # (M·E, n_params): per experiment
            rows = (torch.arange(m)[:, None] * self.ref.batch.size + self.plan.exp_index[None]).flatten()
            p, shared = p_exp[rows], (p_exp, rows)  # (M·S, n_params); one physics matrix per model and experiment
        else:
            p = self._parameters_for(self.params_seg, self.est_raw, m)  # (M·S, n_params)
        u0 = torch.where(self.pinned[None], self.fixed_first[None],
                         torch.clamp(self.seg0 + self.free * self.state_scale, self.lo, self.hi))
        u0 = u0.reshape(m * s, n)
        adjoint = self._adjoint(self.net, m, p, u0, plan, shared)
        fast = None if adjoint is not None else self._drive(self.net, m, p, plan.x_half, shared)  # the same function, fewer operations
        if adjoint is not None:
            traj = adjoint
        elif fast is not None:
            traj = rk4_segments(fast[0], u0, plan, self.box, fast[1])  # (K+1, M·S, n)
        else:
            traj = rk4_segments(self._rhs(self.net, m, p), u0, plan, self.box)
        y_grid = self.problem.compiled.outputs(traj, plan.x_half[0::2], p[None])  # (K+1, M·S, k)
        y_grid = y_grid.reshape(y_grid.shape[0], m, s, -1).movedim(1, 0)  # (M, K+1, S, k)
        ya = y_grid[:, plan.obs_k, plan.obs_s, plan.obs_j]
        yb = y_grid[:, plan.obs_k + 1, plan.obs_s, plan.obs_j]
        pred = ya + plan.obs_w * (yb - ya)
        fit = (((pred - plan.obs_y) / self.out_std[plan.obs_j]) ** 2).mean(-1)
        loss = fit
        if bool(self.has_next.any()):
            last = traj[-1].reshape(m, s, n)
            u0s = u0.reshape(m, s, n)
            gap = (last[:, self.has_next] - u0s[:, plan.next_of[self.has_next]]) / self.state_scale
            loss = loss + self.cont_w * gap.pow(2).mean(dim=(1, 2))
        if self.eq_coef is not None:
            corr = self._corrections(self.net, m, traj, plan.x_half[0::2], p, self._coef(p))  # (K+1, M·S, k)
            corr = corr.reshape(corr.shape[0], m, s, -1) * self.eq_coef[None, None]
            term = (corr.pow(2).mean(dim=(0, 2)).add(1e-30).sqrt() / self.eq_ref).sum(-1)
            loss = loss + torch.where(self.sparsity > 0, self.sparsity * term, torch.zeros_like(term))
        return loss, fit

    def step(self, loss: torch.Tensor, lr: torch.Tensor, rows: torch.Tensor) -> None:
        """Backward over models ``rows`` (finite losses), clip each model's gradient, one AdamW step."""
        for p, *_ in self.params:
            p.grad = None
        loss[rows].sum().backward()
        b1, b2 = self.BETAS
        self.step_count += 1
        bc1 = 1 - b1**self.step_count
        bc2_sqrt = (1 - b2**self.step_count) ** 0.5
        with torch.no_grad():
            grads = []
            for p, mk, _, _ in self.params:
                g = p.grad if p.grad is not None else torch.zeros_like(p)
                grads.append(g if mk is None else torch.where(mk, g, torch.zeros_like(g)))
            # per-model gradient norm over the hybrid's parameters (network, estimates): clip to 10
            norms = [g.flatten(1).norm(dim=1) for g, (_, _, _, clip) in zip(grads, self.params) if clip]
            if norms:
                total = torch.linalg.vector_norm(torch.stack(norms, dim=1), dim=1)
                coef = (self.MAX_NORM / (total + 1e-6)).clamp(max=1.0)
                grads = [g * coef.reshape(-1, *[1] * (g.ndim - 1)) if clip else g
                         for g, (_, _, _, clip) in zip(grads, self.params)]
            for (p, _, decay, _), g, ea, eas in zip(self.params, grads, self.exp_avg, self.exp_avg_sq):
                shape = (-1, *[1] * (p.ndim - 1))
                lr_p = lr.reshape(shape)
                if decay:
                    p.mul_(1 - lr_p * self.weight_decay.reshape(shape))
                ea.lerp_(g, 1 - b1)
                eas.mul_(b2).addcmul_(g, g, value=1 - b2)
                denom = (eas.sqrt() / bc2_sqrt).add_(self.EPS)
                p.add_((-(lr_p / bc1)) * ea / denom)

    # -- the warm start, batched ---------------------------------------------------------------------------
    def warm_fit(self, forced: Forced, *, iterations: int, window: int) -> None:
        """Every model's derivative-matching warm start (:func:`physmend.ude.warmstart.fit_network`)
        as one batched regression; padded entries do not move."""
        m = self.size
        p_exp = self.ref.batch.params[forced.exp_index]
        n_fit = 2 * len(self.net.weights) + (1 if self.est_idx else 0)  # the network, then the estimates
        fit_models(self.problem, forced, self.template.corrected_idx, models=m,
                   corrections=lambda u, x, p: self._corrections(self.net, m, u, x, p, self._coef(p)),
                   parameters=lambda: self._parameters_for(p_exp, self.est_raw, m),
                   typical=torch.stack([mem.hybrid.rate_scale * mem.hybrid.out_mask for mem in self.members]), params=[p for p, *_ in self.params[:n_fit]],
                   masks=[mk for _, mk, *_ in self.params[:n_fit]], iterations=iterations, window=window)
        for p, *_ in self.params:
            p.grad = None

    def chain_starts(self) -> None:
        """After the batched warm start: the segment starts of every warm-started model that asks for
        it (``train.segment_starts: chained``) chained by its own hybrid, as train() does. They follow
        from the warm start and the shooting plan alone: a model whose warm start an earlier stack of
        this process had, on the same plan, reuses that stack's chained starts; models of one warm
        start in this stack are chained once."""
        want = [i for i, mem in enumerate(self.members) if mem.forced is not None and mem.cfg.train.chained]
        if not want:
            return
        name = ("chained", plan_key(self.plan))
        pending = []
        for i in want:
            key = self.members[i].warm_key
            stored = None if key is None else recall_derived(key, name)
            if stored is not None:
                self.seg0[i] = stored
            else:
                pending.append(i)
        firsts = same_warm_start([self.members[i].warm_key for i in pending])
        todo = [i for j, i in enumerate(pending) if firsts[j] == j]
        same = {i: pending[firsts[j]] for j, i in enumerate(pending) if firsts[j] != j}  # -> the model chained for it
        if not todo:
            return
        m = len(todo)
        rows = torch.tensor(todo, dtype=torch.long)
        s, n = self.seg0.shape[1:]
        with torch.no_grad():
            est = None if self.est_raw is None else self.est_raw.detach()[rows]
            p = self._parameters_for(self.params_seg, est, m)
            u0 = torch.where(self.plan.first[None, :, None], self.fixed_first[None], self.seg0[rows]).reshape(m * s, n)
            keep = next(mem.forced.measured for mem in self.members if mem.forced is not None)
            plan = dataclasses.replace(self.plan, x_half=self.plan.x_half.repeat(1, m, 1))
            chained = chained_starts(self._rhs(self.net.select(rows), m, p), u0, plan, models=m, keep=keep).reshape(m, s, n)
        for j, i in enumerate(todo):
            self.seg0[i] = chained[j]
            key = self.members[i].warm_key
            if key is not None:
                remember_derived(key, name, chained[j].clone())
        for i, first in same.items():
            self.seg0[i] = self.seg0[first]
