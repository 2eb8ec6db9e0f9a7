"""Several hybrid models (a group of sweep trials) trained together in one batched solve.

On small ODEs, per-operation dispatch, not arithmetic, dominates an epoch: a stack of ``M``
same-shaped networks costs about as much as one (the 2-state oscillator of the tests: 16 models
per epoch for twice the time of one). On larger ones arithmetic takes over from a few models on
(the 28-state cargo box: about 2.5-3x less time per model from M = 4 to 32; padding mixed widths
and depths to the largest costs part of that, see ``stack_key(architecture=True)``).
:func:`train_stack` trains ``M`` configurations
as one multiple-shooting solve over ``M·S`` rows (``S`` segments per model) and evaluates the
still-active models in one whole-trajectory solve over ``M·B`` rows (``B`` train and validation
experiments; test experiments only at the end); their derivative-matching warm starts are one
batched regression over shared forced trajectories. Yet every model remains exactly its own
trial, as :func:`physmend.ude.train.train` would run it:

* its own architecture ``(width, depth, activation)``: networks are padded to the largest width
  and depth of the stack; padded units have zero weights that never move (their gradients are
  masked, so neither AdamW nor weight decay touches them), a shallower network skips the extra
  hidden layers (``h ← h``), and each model's rows pass through its own activation;
* its own initialisation (seed) and warm start, built on its own :class:`HybridModel` exactly as
  ``train()`` builds it, then copied into the padded tensors;
* its own AdamW (learning rate, weight decay, schedule and warm-up ramp), gradient clipping
  (norm 10 per model), trainable segment starts and jointly estimated parameters;
* its own evaluations, early stopping, best checkpoint and report callback; a model that stops
  (patience, divergence, an exception raised by ``report``) leaves the stack, the others go on;
* its own :class:`TrainResult` at the end, with an ordinary :class:`HybridModel` of its own
  architecture (artifacts and reloading are unchanged).

What cannot be identical: batched matrix products (``baddbmm``) and reductions over padded
tensors round differently from ``nn.Linear`` on one model (differences ~1e-15 relative per step),
and the adaptive whole-trajectory solver picks one step size for all rows of a batched
evaluation, so checkpoint metrics agree with a solo evaluation to the solver tolerance. The final
metrics of each model come from its own solo evaluation, exactly as ``train()`` computes them, or
(``final_eval="batched"``, as sweeps use it) from one batched solve of all finished models.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from physmend.problem import Problem
from physmend.simulate import Batch, make_batch
from physmend.ude.hybrid import ACTIVATIONS, HybridModel, HybridSpec, UDEConfigError
from physmend.ude.train import (
    Reference,
    Shooting,
    TrainingDiverged,
    TrainResult,
    _chain,
    _equation_scale,
    _evaluate,
    _initial_segments,
    _output_spread,
    _pooled,
    _sim_opts,
    _train_mask,
    _val_mask,
    artifacts_of,
    build_spec,
    chained_starts,
    checkpoint_problem,
    fit_figures,
    lr_factor,
    metrics_of,
    plan_shooting,
    reference,
    rk4_segments,
    simulate_with,
)
from physmend.ude.warmstart import (
    Forced,
    fit_models,
    forced_trajectories,
    recall,
    recall_derived,
    remember,
    remember_derived,
    segment_starts,
    warm_key,
    warm_start,
)

__all__ = ["SHARED_KEYS", "stack_key", "train_stack"]

#: Settings every model of one stack must share: they shape the common solve (or the problem).
SHARED_KEYS: tuple[str, ...] = (
    "model",
    "data",
    "simulate",
    "train.step",
    "train.segment_length",
    "train.segment_samples",
    "train.epochs",
    "train.schedule",
    "train.eval_every",
    "train.patience",
    "train.continuity_weight",
    "train.estimate_parameters",
    "ude.corrected",
    "ude.inputs",
)
_LINEAR_KEY = "ude.depth == 0"  # a linear correction (no hidden layer) cannot be padded into an MLP

Report = Callable[[int, int, dict[str, float]], None]


def _plain(value: Any) -> Any:
    """A hashable, comparable form of a config value (containers as canonical JSON)."""
    if isinstance(value, DictConfig) or OmegaConf.is_list(value):
        return json.dumps(OmegaConf.to_container(value, resolve=True), sort_keys=True)
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, sort_keys=True)
    return value


def stack_key(cfg: DictConfig, *, architecture: bool = False) -> tuple[tuple[str, Any], ...]:
    """The settings that must agree for configurations to train in one stack, as ``(key, value)`` pairs.

    Trials whose keys are equal can be passed together to :func:`train_stack`; they may differ in
    ``seed``, ``ude.width``, ``ude.depth`` (all ≥ 1, or all 0), ``ude.activation``,
    ``ude.output_scale``, ``train.lr``, ``train.weight_decay``, ``train.sparsity`` and the
    warm-start settings. ``architecture=True`` adds width, depth and activation to the key: stacks
    of one architecture need no padding, which pays where arithmetic, not dispatch, dominates.
    """
    pairs = [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in SHARED_KEYS]
    pairs.append((_LINEAR_KEY, int(cfg.ude.depth) == 0))
    if architecture:
        pairs += [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in ("ude.width", "ude.depth", "ude.activation")]
    return tuple(pairs)


def _check_shared(cfgs: Sequence[DictConfig]) -> None:
    first = dict(stack_key(cfgs[0]))
    for i, cfg in enumerate(cfgs[1:], 1):
        for key, value in stack_key(cfg):
            if value != first[key]:
                raise UDEConfigError(
                    f"train_stack: every model of a stack must have the same `{key}` (it shapes the shared solve), "
                    f"but model 0 has {first[key]!r} and model {i} has {value!r}; group trials by stack_key()"
                )


# -- the padded networks ----------------------------------------------------------------------------
def _linears(hybrid: HybridModel) -> list[nn.Linear]:
    return [m for m in hybrid.net if isinstance(m, nn.Linear)]


@dataclass
class _Net:
    """``M`` MLPs padded to one shape: layer ``l`` maps ``h (M, N, a)`` to ``baddbmm(b, h, W)``.

    Shapes: ``weights[l] (M, a_l, b_l)`` (transposed ``nn.Linear`` weights), ``biases[l] (M, 1, b_l)``;
    ``use[l] (M, 1, 1)`` False where a model has fewer hidden layers (the layer is skipped) or None;
    ``activations`` each model's activation name: models are ordered so that each activation's
    models are consecutive, and every activation runs on its own models only;
    ``scale (M, 1, k)`` the output scale times the output mask.
    """

    weights: list[torch.Tensor]
    biases: list[torch.Tensor]
    use: list[torch.Tensor | None]
    activations: list[str]
    scale: torch.Tensor
    runs: list[tuple[nn.Module, int, int]] = field(init=False)  # (activation, first model, end)

    def __post_init__(self) -> None:
        self.runs = []
        for i, name in enumerate(self.activations):
            if self.runs and self.activations[i - 1] == name:
                act, start, _ = self.runs[-1]
                self.runs[-1] = (act, start, i + 1)
            else:
                self.runs.append((ACTIVATIONS[name](), i, i + 1))

    def activation(self, a: torch.Tensor) -> torch.Tensor:
        if len(self.runs) == 1:
            return self.runs[0][0](a)
        if not torch.is_grad_enabled():  # evaluations: in place, no concatenation (``a`` is a fresh product)
            for act, start, end in self.runs:
                a[start:end] = act(a[start:end])
            return a
        return torch.cat([act(a[start:end]) for act, start, end in self.runs])

    def __call__(self, z: torch.Tensor) -> torch.Tensor:
        """Corrections ``(M, N, k)`` of normalised features ``z (M, N, n_in)``."""
        h = z
        last = len(self.weights) - 1
        for l, (w, b) in enumerate(zip(self.weights, self.biases)):
            a = torch.baddbmm(b, h, w)
            if l == last:
                return a * self.scale
            a = self.activation(a)
            use = self.use[l]
            h = a if use is None else torch.where(use, a, h)
        raise AssertionError("a network has an output layer")

    def select(self, rows: torch.Tensor) -> _Net:
        """The networks of stack rows ``rows`` (no gradients)."""
        return _Net(
            weights=[w.detach()[rows] for w in self.weights],
            biases=[b.detach()[rows] for b in self.biases],
            use=[None if u is None else u[rows] for u in self.use],
            activations=[self.activations[i] for i in rows.tolist()],
            scale=self.scale[rows],
        )


def _pad_networks(hybrids: Sequence[HybridModel], dtype: torch.dtype) -> tuple[_Net, list[torch.Tensor | None]]:
    """Padded stacked networks copied from ``hybrids``, and boolean masks of each layer's real entries."""
    m = len(hybrids)
    specs = [h.spec for h in hybrids]
    depths = [len(s.widths) for s in specs]
    if len({d == 0 for d in depths}) > 1:
        raise UDEConfigError(f"train_stack: ude.depth=0 (a linear correction) cannot share a stack with deeper networks, "
                             f"but got depths {depths}")
    depth = max(depths)
    n_in, n_out = specs[0].n_inputs, len(specs[0].corrected)
    width = max((w for s in specs for w in s.widths), default=0)
    dims = [(n_in if l == 0 else width, width) for l in range(depth)] + [(width if depth else n_in, n_out)]
    weights = [torch.zeros(m, a, b, dtype=dtype) for a, b in dims]
    biases = [torch.zeros(m, 1, b, dtype=dtype) for _, b in dims]
    w_mask = [torch.zeros(m, a, b, dtype=torch.bool) for a, b in dims]
    b_mask = [torch.zeros(m, 1, b, dtype=torch.bool) for _, b in dims]
    with torch.no_grad():
        for i, hybrid in enumerate(hybrids):
            lins = _linears(hybrid)
            slots = list(range(len(lins) - 1)) + [depth]  # the output layer is always the last one
            for lin, l in zip(lins, slots):
                a, b = lin.in_features, lin.out_features
                weights[l][i, :a, :b] = lin.weight.T
                biases[l][i, 0, :b] = lin.bias
                w_mask[l][i, :a, :b] = True
                b_mask[l][i, 0, :b] = True
    use: list[torch.Tensor | None] = []
    for l in range(depth):
        rows = torch.tensor([d > l for d in depths]).reshape(m, 1, 1)
        use.append(None if bool(rows.all()) else rows)
    scale = torch.stack([h.out_scale * h.out_mask for h in hybrids])[:, None, :].to(dtype)
    net = _Net(weights, biases, use, [s.activation for s in specs], scale)
    masks: list[torch.Tensor | None] = []
    for mk in [x for pair in zip(w_mask, b_mask) for x in pair]:
        masks.append(None if bool(mk.all()) else mk)
    return net, masks


def _write_back(net: _Net, row: int, hybrid: HybridModel, est_raw: torch.Tensor | None) -> None:
    """Copy stack row ``row`` into ``hybrid``'s own (unpadded) layers and estimates."""
    lins = _linears(hybrid)
    depth = len(net.weights) - 1
    slots = list(range(len(lins) - 1)) + [depth]
    with torch.no_grad():
        for lin, l in zip(lins, slots):
            a, b = lin.in_features, lin.out_features
            lin.weight.copy_(net.weights[l].detach()[row, :a, :b].T)
            lin.bias.copy_(net.biases[l].detach()[row, 0, :b])
        if est_raw is not None:
            hybrid.est_raw.copy_(est_raw.detach()[row])


def _plan_key(plan: Shooting) -> tuple[Any, ...]:
    """What identifies a shooting plan's segments (step, steps per segment, starts, experiments)."""
    return (plan.dt, plan.steps, tuple(plan.starts.tolist()), tuple(plan.exp_index.tolist()))


#: reference simulations and shooting plans of the last few problems this process trained on: every
#: stack of a sweep shares them (they depend on the problem and the solver and shooting settings only)
_SETUPS: dict[int, tuple[Problem, dict[Any, Reference], dict[Any, Shooting]]] = {}
_SETUPS_MAX = 4


def _setup(problem: Problem, cfg: DictConfig, *, plan: bool = True) -> tuple[Reference, Shooting | None]:
    """``(reference(problem, cfg), plan_shooting(problem, ref.batch, cfg))``, computed once per
    problem, solver settings and shooting settings in this process (``plan=False``: no plan)."""
    entry = _SETUPS.get(id(problem))
    if entry is None or entry[0] is not problem:
        if len(_SETUPS) >= _SETUPS_MAX:
            _SETUPS.pop(next(iter(_SETUPS)))
        entry = _SETUPS[id(problem)] = (problem, {}, {})
    _, refs, plans = entry
    ref_key = json.dumps(_sim_opts(cfg), sort_keys=True, default=str)
    ref = refs.get(ref_key)
    if ref is None:
        ref = refs[ref_key] = reference(problem, cfg)
    if not plan:
        return ref, None
    plan_key = (ref_key, float(cfg.train.step), float(cfg.train.segment_length))
    shooting = plans.get(plan_key)
    if shooting is None:
        shooting = plans[plan_key] = plan_shooting(problem, ref.batch, cfg)
    return ref, shooting


def _time_grid_parts(problem: Problem, batch: Batch) -> list[tuple[list[int], Batch, torch.Tensor | None]]:
    """``batch``'s experiments in sets that share their times and input knots: ``(indices into batch,
    their own batch, their times' rows in batch.t)``; one set ``(all, batch, None)`` when all share.

    An adaptive solve of a batch ends steps on every evaluation time and input knot of every row;
    experiments recorded on different clocks would each take the steps of all. Solved per set, each
    takes only its own."""
    sets: list[tuple[list[int], tuple[tuple[float, ...], tuple[float, ...]]]] = []
    for b, e in enumerate(problem.experiments):
        own = make_batch([e], problem.compiled, problem.dtype)
        grid = (tuple(own.t.tolist()), tuple(own.inputs.knots.tolist()))
        for members, key in sets:
            if key == grid:
                members.append(b)
                break
        else:
            sets.append(([b], grid))
    if len(sets) == 1:
        return [(list(range(batch.size)), batch, None)]
    parts = []
    for members, _ in sets:
        part = make_batch([problem.experiments[b] for b in members], problem.compiled, problem.dtype)
        parts.append((members, part, torch.searchsorted(batch.t, part.t)))
    return parts


# -- one model's bookkeeping ------------------------------------------------------------------------
@dataclass
class _Member:
    """One trial of the stack: everything that is its own outside the stacked tensors."""

    slot: int  # index into cfgs (and the result list)
    cfg: DictConfig
    hybrid: HybridModel
    forced: Forced | None
    seg0: torch.Tensor  # (S, n)
    lrs: list[float]  # learning rate of epochs 1..E (as train()'s scheduler gives them)
    history: list[dict[str, float]] = field(default_factory=list)
    best: tuple[float, dict[str, Any], dict[str, float]] | None = None
    since_best: int = 0
    outcome: BaseException | None = None  # set when the model stops with an error
    done: bool = False
    warm_key: str | None = None  # its stored warm start (:func:`physmend.ude.warmstart.warm_key`), if batched


def _lr_schedule(cfg: DictConfig, *, warm: bool) -> list[float]:
    """The learning rate of every epoch, from the optimiser/scheduler pair train() uses."""
    tc = cfg.train
    epochs = int(tc.epochs)
    dummy = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([dummy], lr=float(tc.lr))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor(tc, epochs, warm=warm))
    lrs = []
    for _ in range(epochs):
        lrs.append(float(opt.param_groups[0]["lr"]))
        opt.step()  # no gradient: nothing moves; keeps the scheduler's step-order check quiet
        sched.step()
    return lrs


# -- the stack -----------------------------------------------------------------------------------------
class _Stack:
    """The active models' stacked trainable tensors, their AdamW state, and the batched solves."""

    BETAS = (0.9, 0.999)
    EPS = 1e-8
    MAX_NORM = 10.0

    def __init__(self, members: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig) -> None:
        order = list(ACTIVATIONS)  # models of one activation side by side (see _Net)
        members = sorted(members, key=lambda mem: order.index(mem.hybrid.spec.activation))
        self.members = members
        self.problem = problem
        self.ref = ref
        self.plan = plan
        self.template = members[0].hybrid  # index lists, normalisation: the same for every model
        dtype = problem.dtype
        self.dtype = dtype
        self.net, masks = _pad_networks([m.hybrid for m in members], dtype)
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
        self.sparsity = torch.tensor([float(m.cfg.train.get("sparsity", 0.0)) for m in members], dtype=dtype)
        self.mean = self.template.mean
        self.std = self.template.std
        # shared pieces of the training solve (as in train())
        tm = _train_mask(problem, ref.batch)
        self.fixed_first = ref.batch.u0[plan.exp_index]
        self.state_scale = ref.states[tm].std(0).clamp_min(1e-3)
        self.out_std = _output_spread(ref.batch.obs[tm])
        self.params_seg = ref.batch.params[plan.exp_index]
        self.has_next = plan.next_of >= 0
        self.cont_w = float(cfg.train.continuity_weight)
        self.eq_coef, self.eq_ref = (_equation_scale(problem, self.spec, self.params_seg, ref)
                                     if bool((self.sparsity > 0).any()) and self.spec.corrected else (None, None))
        self.checked = checkpoint_problem(problem)  # checkpoints simulate train/validation experiments only
        self.eval_batch = make_batch(self.checked.experiments, problem.compiled, dtype)
        self.full_batch = self.eval_batch if self.checked is problem else make_batch(problem.experiments, problem.compiled, dtype)
        self.parts = _time_grid_parts(self.checked, self.eval_batch)
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

    def _corrections(self, net: _Net, m: int, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Corrections ``(..., m·R, k)`` of ``u (..., m·R, n)``: each model's rows through its own network."""
        z = (self.template.features(u, x, p) - self.mean) / self.std
        *lead, rows, n_feat = z.shape
        r = rows // m
        if not lead:
            return net(z.reshape(m, r, n_feat)).reshape(rows, -1)
        zz = z.reshape(*lead, m, r, n_feat).movedim(-3, 0).reshape(m, -1, n_feat)
        out = net(zz)
        return out.reshape(m, *lead, r, -1).movedim(0, -3).reshape(*lead, rows, -1)

    def _rhs(self, net: _Net, m: int, p: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``f(u, x) -> du/dt`` over stacked rows, structured as :meth:`HybridModel.rhs`."""
        physics = self.problem.compiled.bind(p)
        idx = self.template.corrected_idx
        n = len(self.problem.compiled.state_names)
        if not idx:
            return physics
        if len(idx) == n and idx == list(range(n)):
            return lambda u, x: physics(u, x) + self._corrections(net, m, u, x, p)
        index = torch.tensor(idx, dtype=torch.long)

        def f(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
            corr = self._corrections(net, m, u, x, p)
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
        p = self._parameters_for(self.params_seg, self.est_raw, m)  # (M·S, n_params)
        u0 = torch.where(self.plan.first[None, :, None], self.fixed_first[None], self.seg0 + self.free * self.state_scale)
        u0 = u0.reshape(m * s, n)
        traj = rk4_segments(self._rhs(self.net, m, p), u0, plan)  # (K+1, M·S, n)
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
            corr = self._corrections(self.net, m, traj, plan.x_half[0::2], p)  # (K+1, M·S, k)
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
                   corrections=lambda u, x, p: self._corrections(self.net, m, u, x, p),
                   parameters=lambda: self._parameters_for(p_exp, self.est_raw, m),
                   typical=self.net.scale[:, 0, :], params=[p for p, *_ in self.params[:n_fit]],
                   masks=[mk for _, mk, *_ in self.params[:n_fit]], iterations=iterations, window=window)
        for p, *_ in self.params:
            p.grad = None

    def chain_starts(self) -> None:
        """After the batched warm start: the segment starts of every warm-started model that asks for
        it (``train.segment_starts: chained``) chained by its own hybrid, as train() does. They follow
        from the warm start and the shooting plan alone: a model whose warm start an earlier stack of
        this process had, on the same plan, reuses that stack's chained starts."""
        want = [i for i, mem in enumerate(self.members) if mem.forced is not None and _chain(mem.cfg.train)]
        if not want:
            return
        name = ("chained", _plan_key(self.plan))
        todo = []
        for i in want:
            key = self.members[i].warm_key
            stored = None if key is None else recall_derived(key, name)
            if stored is None:
                todo.append(i)
            else:
                self.seg0[i] = stored
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

    # -- evaluation ----------------------------------------------------------------------------------------
    def evaluate(self, positions: list[int], sim: dict[str, Any], *, full: bool = False
                 ) -> list[tuple[dict[str, float], torch.Tensor] | BaseException]:
        """Whole-trajectory metrics of the models at ``positions`` in one batched solve (per model on failure).

        Checkpoints simulate the train and validation experiments; ``full`` every experiment
        (test ones included), as a final evaluation does, with outputs at every time of the batch
        (for figures). Checkpoint experiments recorded at different times are solved apart
        (:func:`_time_grid_parts`): each set of rows takes only its own steps.
        """
        m = len(positions)
        problem = self.problem if full else self.checked
        batch = self.full_batch if full else self.eval_batch
        b = batch.size
        rows = torch.tensor(positions, dtype=torch.long)
        net = self.net.select(rows)
        est = None if self.est_raw is None else self.est_raw.detach()[rows]
        parts = [(list(range(b)), batch, None)] if full else self.parts
        try:
            with torch.no_grad():
                if len(parts) == 1:
                    y = self._simulate(net, est, positions, batch, sim)
                else:  # (T, M, B, k) on the union of times; each experiment set only where it has times
                    y = torch.full((batch.t.shape[0], m, b, len(self.problem.compiled.output_names)), math.nan,
                                   dtype=self.dtype)
                    for exps, part, at in parts:
                        y_part = self._simulate(net, est, positions, part, sim)
                        y[at[:, None], :, torch.tensor(exps)[None, :]] = y_part.reshape(-1, m, len(exps), y.shape[-1]).movedim(1, 2)
                    y = y.reshape(y.shape[0], m * b, -1)
        except Exception:  # noqa: BLE001 - one model's failure must not end the others: solve each alone
            return [self._evaluate_alone(i, sim, problem) for i in positions]
        out: list[tuple[dict[str, float], torch.Tensor] | BaseException] = []
        for j in range(m):
            y_j = y[:, j * b:(j + 1) * b]
            try:
                out.append((metrics_of(problem, batch, y_j), y_j))
            except TrainingDiverged as exc:
                out.append(exc)
        return out

    def _simulate(self, net: _Net, est: torch.Tensor | None, positions: list[int], batch: Batch,
                  sim: dict[str, Any]) -> torch.Tensor:
        """Outputs ``(T, M·B, k)`` of the models at ``positions`` (networks ``net``, estimates ``est``)
        on every experiment of ``batch``, rows model-major, in one adaptive solve."""
        m, b = len(positions), batch.size
        rep = torch.arange(b).repeat(m)
        names = [f"{self.members[i].slot}:{e}" for i in positions for e in batch.ids]
        batch_m = dataclasses.replace(batch, ids=names, inputs=batch.inputs.select(rep), params=batch.params[rep],
                                      u0=batch.u0[rep], obs=batch.obs[:, rep], split_time=batch.split_time[rep])
        p = self._parameters_for(batch.params, est, m)  # (M·B, n_params)
        states = simulate_with(self._rhs(net, m, p), batch_m, batch_m.u0, sim)
        return self.problem.compiled.outputs(states, batch_m.inputs.at(batch.t), p[None])  # (T, M·B, k)

    def _evaluate_alone(self, position: int, sim: dict[str, Any], problem: Problem
                        ) -> tuple[dict[str, float], torch.Tensor] | BaseException:
        member = self.members[position]
        self.write_back(position)
        try:
            metrics, y, _ = _evaluate(member.hybrid, problem, sim)
        except Exception as exc:  # noqa: BLE001 - what train() would have raised for this model
            return exc
        return metrics, y

    def write_back(self, position: int) -> None:
        _write_back(self.net, position, self.members[position].hybrid, self.est_raw)


# -- training ------------------------------------------------------------------------------------------------
def _prepare(cfg: DictConfig, problem: Problem, ref: Reference, plan: Shooting, slot: int, *, warm: bool = True) -> _Member:
    """One model exactly as train() starts it: seed, spec, network, warm start (``warm``; otherwise
    the stack does it, batched), segment starts."""
    torch.manual_seed(int(cfg.get("seed", 0)))
    spec = build_spec(cfg, problem, ref)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    seg0 = _initial_segments(problem, ref, plan)
    chain = _chain(cfg.train)
    forced = warm_start(hybrid, problem, ref.batch, cfg) if warm else None
    if forced is not None:
        seg0 = segment_starts(forced, plan.exp_index, plan.starts, seg0)
        if chain:
            params_seg = ref.batch.params[plan.exp_index]
            u0 = torch.where(plan.first[:, None], ref.batch.u0[plan.exp_index], seg0)
            seg0 = chained_starts(hybrid.rhs(hybrid.parameters_for(params_seg)), u0, plan, keep=forced.measured)
    return _Member(slot=slot, cfg=cfg, hybrid=hybrid, forced=forced, seg0=seg0,
                   lrs=_lr_schedule(cfg, warm=forced is not None))


def _warm_settings(cfg: DictConfig) -> tuple[str, int, int]:
    """``(train.warm_start, warm_iterations, window in grid steps)``: as :func:`warm_start` reads them."""
    tc = cfg.train
    window = max(1, int(round(float(tc.get("warm_window", 0.0)) / float(tc.step))))
    return str(tc.get("warm_start", "auto")), int(tc.get("warm_iterations", 400)), window


def _shared_warm_start(members: list[_Member], problem: Problem, ref: Reference, plan: Shooting) -> tuple[Forced, int, int] | None:
    """The warm start every model asks for (``auto``, the same settings): the forced trajectories
    (computed once: they depend only on the records and the initial parameter estimates, which the
    stack shares), with each member's segment starts and schedule set as :func:`_prepare` would;
    None where no output is a state (no warm start, as alone)."""
    _, iterations, window = _warm_settings(members[0].cfg)
    forced = forced_trajectories(problem, ref.batch, members[0].hybrid, float(members[0].cfg.train.step))
    if forced is None:
        return None
    for mem in members:
        mem.forced = forced
        mem.seg0 = segment_starts(forced, plan.exp_index, plan.starts, mem.seg0)
        mem.lrs = _lr_schedule(mem.cfg, warm=True)
    return forced, iterations, window


def _warm_fit(members: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig,
              forced: Forced, iterations: int, window: int) -> None:
    """Every member's warm start: one batched regression of the models this process has not
    warm-started before (:func:`physmend.ude.warmstart.warm_key`: same network as initialised, data
    and settings); the others reuse the stored result, which is what the regression would give."""
    p_exp = ref.batch.params[forced.exp_index]
    keys = [warm_key(mem.hybrid, forced, p_exp, iterations, window) for mem in members]
    todo: dict[str, _Member] = {}
    for mem, key in zip(members, keys):
        if key not in todo and not recall(key, mem.hybrid):
            todo[key] = mem
    if todo:
        sub = _Stack(list(todo.values()), problem, ref, plan, cfg)
        sub.warm_fit(forced, iterations=iterations, window=window)
        for pos in range(sub.size):
            sub.write_back(pos)
        for key, mem in todo.items():
            remember(key, mem.hybrid)
    for mem, key in zip(members, keys):
        mem.warm_key = key
        if key in todo and todo[key] is not mem:
            recall(key, mem.hybrid)


def _check_same_shape(members: list[_Member]) -> None:
    a = members[0].hybrid.spec
    for mem in members[1:]:
        s = mem.hybrid.spec
        same = (s.corrected == a.corrected and s.input_names == a.input_names and s.estimated == a.estimated
                and s.mean == a.mean and s.std == a.std)
        if not same:
            raise UDEConfigError(f"train_stack: model {mem.slot} corrects or reads other variables than model "
                                 f"{members[0].slot} (ude.corrected / ude.inputs / train.estimate_parameters must agree)")


def train_stack(cfgs: Sequence[DictConfig], problem: Problem, *, report: Report | None = None,
                final_eval: str = "own", figures: bool = True) -> list[TrainResult | BaseException]:
    """Train one hybrid model per configuration, all in one batched solve (see module docstring).

    Args:
        cfgs: one full configuration per model. They may differ in ``seed``, ``ude.width``,
            ``ude.depth``, ``ude.activation``, ``ude.output_scale``, ``train.lr``,
            ``train.weight_decay``, ``train.sparsity`` and the warm-start settings; everything in
            :data:`SHARED_KEYS` must agree (see :func:`stack_key`). Models with the same warm-start
            settings are warm-started together, as one batched regression.
        problem: the problem every model is trained on.
        report: ``report(i, epoch, row)`` after every evaluation of model ``i`` (``row`` as the
            ``report`` of :func:`physmend.ude.train.train` gets it). An exception it raises stops
            model ``i`` only and becomes its result.
        final_eval: ``"own"``: each model's final metrics come from its own solo evaluation, exactly as
            ``train()`` computes them (a reloaded model reproduces them); costs one solo solve per
            model. ``"batched"``: the best checkpoints of all finished models are simulated on every
            experiment in one batched solve (the adaptive solver takes the steps the most demanding
            model needs, so each agrees with its solo evaluation to the solver tolerance).
        figures: attach the fit figures (one per experiment) to each result.

    Returns:
        One entry per configuration, in order: the model's :class:`TrainResult` (as
        :func:`physmend.ude.train.train` would return it), or the exception that stopped it —
        :class:`TrainingDiverged` when its loss or trajectory became non-finite, the exception
        raised by ``report``, or an error of its own settings.

    Raises:
        UDEConfigError: the configurations differ in a shared setting (the message names the key).
    """
    if final_eval not in ("own", "batched"):
        raise UDEConfigError(f"final_eval must be 'own' or 'batched', but got {final_eval!r}")
    if not cfgs:
        return []
    from physmend.ude.timescale import check_budget, resolve_times

    _check_shared(cfgs)
    ref, _ = _setup(problem, cfgs[0], plan=False)
    cfgs = [resolve_times(cfg, problem, ref) for cfg in cfgs]  # 'auto' time settings, as train() resolves them
    cfg0 = cfgs[0]
    ref, plan = _setup(problem, cfg0)
    check_budget(plan, problem, cfgs)
    results: list[TrainResult | BaseException | None] = [None] * len(cfgs)
    members: list[_Member] = []
    warm_settings = {_warm_settings(cfg) for cfg in cfgs}
    batched_warm = len(warm_settings) == 1 and next(iter(warm_settings))[0] == "auto"
    for i, cfg in enumerate(cfgs):
        try:
            members.append(_prepare(cfg, problem, ref, plan, i, warm=not batched_warm))
        except Exception as exc:  # noqa: BLE001 - train(cfg) would have raised it: this trial's outcome
            results[i] = exc
    if members:
        _check_same_shape(members)
        warm = _shared_warm_start(members, problem, ref, plan) if batched_warm else None
        finished = _run(members, problem, ref, plan, cfg0, report, warm)
        sim = _sim_opts(cfg0)
        done = [mem for mem in finished if mem.outcome is None]
        final = _final_batched(done, problem, ref, plan, cfg0, sim) if final_eval == "batched" and done else {}
        for mem in finished:
            results[mem.slot] = mem.outcome if mem.outcome is not None else _result(mem, problem, ref, sim, final.get(mem.slot), figures)
    assert all(r is not None for r in results)
    return results  # type: ignore[return-value]


def _run(members: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig,
         report: Report | None, warm: tuple[Forced, int, int] | None = None) -> list[_Member]:
    """The shared epoch loop (after the batched warm start ``warm``: forced trajectories, iterations,
    window); returns every member, each with a best checkpoint or an outcome."""
    tc = cfg.train
    if warm is not None:
        _warm_fit(members, problem, ref, plan, cfg, *warm)
    stack = _Stack(members, problem, ref, plan, cfg)
    if warm is not None:
        stack.chain_starts()
    sim = _sim_opts(cfg)
    checked_name = ("checkpoint", json.dumps(sim, sort_keys=True, default=str), id(problem))
    epochs = int(tc.epochs)
    eval_every = max(1, int(tc.eval_every))
    patience = int(tc.patience)

    def checkpoint(positions: list[int], epoch: int, loss: torch.Tensor | None, fit: torch.Tensor | None,
                   known: dict[int, dict[str, float]] | None = None) -> None:
        """Evaluate the models at ``positions`` (``known``: metrics of some already, by position); mark
        those whose patience ran out or that failed as done."""
        known = known or {}
        todo = [pos for pos in positions if pos not in known]
        outcomes: dict[int, tuple[dict[str, float], Any] | BaseException] = {pos: (known[pos], None) for pos in positions if pos in known}
        if todo:
            outcomes.update(zip(todo, stack.evaluate(todo, sim)))
        for pos in positions:
            outcome = outcomes[pos]
            mem = stack.members[pos]
            if isinstance(outcome, BaseException):
                mem.outcome, mem.done = outcome, True
                continue
            metrics, _ = outcome
            if epoch == 0 and pos not in known and mem.warm_key is not None:
                remember_derived(mem.warm_key, checked_name, (problem, dict(metrics)))
            row = {"epoch": float(epoch),
                   "loss": float("nan") if loss is None else float(loss[pos]),
                   "fit_loss": float("nan") if fit is None else float(fit[pos]),
                   **{k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")}}
            mem.history.append(row)
            if mem.best is None or metrics["val.rmse"] < mem.best[0]:
                stack.write_back(pos)
                mem.best = (metrics["val.rmse"], copy.deepcopy(mem.hybrid.state_dict()), metrics)
                mem.since_best = 0
            else:
                mem.since_best += 1
            if report is not None:
                try:
                    report(mem.slot, epoch, row)
                except Exception as exc:  # noqa: BLE001 - e.g. a pruning signal: this model stops
                    mem.outcome, mem.done = exc, True
                    continue
            if patience > 0 and mem.since_best >= patience:
                mem.done = True

    def drop_done() -> None:
        stack.keep([i for i, mem in enumerate(stack.members) if not mem.done])

    warm = [i for i, mem in enumerate(stack.members) if mem.forced is not None]
    if warm:  # a warm start itself is a candidate (it may already be the best fit), as in train()
        # its evaluation follows from the warm start alone: an earlier stack of this process may have it
        known = {}
        for pos in warm:
            key = stack.members[pos].warm_key
            stored = None if key is None else recall_derived(key, checked_name)
            if stored is not None and stored[0] is problem:
                known[pos] = dict(stored[1])
        checkpoint(warm, 0, None, None, known)
        drop_done()
    for epoch in range(1, epochs + 1):
        if not stack.members:
            break
        loss, fit = stack.losses()
        ok = torch.isfinite(loss.detach())
        for pos in torch.nonzero(~ok).flatten().tolist():
            mem = stack.members[pos]
            lr0 = float(mem.cfg.train.lr)
            mem.outcome = TrainingDiverged(f"training loss became non-finite at epoch {epoch} (lr {lr0:g}); "
                                           "try a smaller train.lr or train.step")
            mem.done = True
        if bool(ok.any()):
            lr = torch.tensor([mem.lrs[epoch - 1] for mem in stack.members], dtype=stack.dtype)
            stack.step(loss, lr, torch.nonzero(ok).flatten())
        loss, fit = loss.detach(), fit.detach()
        if epoch % eval_every == 0 or epoch == epochs:
            live = [i for i, mem in enumerate(stack.members) if not mem.done]
            if live:
                checkpoint(live, epoch, loss, fit)
        drop_done()
    return members


def _final_batched(done: list[_Member], problem: Problem, ref: Reference, plan: Shooting, cfg: DictConfig,
                   sim: dict[str, Any]) -> dict[int, tuple[dict[str, float], torch.Tensor] | BaseException]:
    """Every finished model's best checkpoint simulated on every experiment in one batched solve, by slot."""
    for mem in done:
        assert mem.best is not None
        mem.hybrid.load_state_dict(mem.best[1])
    stack = _Stack(done, problem, ref, plan, cfg)  # sorted by activation: map results back by slot
    outcomes = stack.evaluate(list(range(stack.size)), sim, full=True)
    return {mem.slot: outcome for mem, outcome in zip(stack.members, outcomes)}


def _result(mem: _Member, problem: Problem, ref: Reference, sim: dict[str, Any],
            final: tuple[dict[str, float], torch.Tensor] | BaseException | None, figures: bool) -> TrainResult | BaseException:
    """The model's best checkpoint as train() returns it: its own HybridModel, evaluated on its own
    (``final`` None) or with the metrics of the final batched evaluation."""
    assert mem.best is not None
    hybrid = mem.hybrid
    hybrid.load_state_dict(mem.best[1])
    if isinstance(final, BaseException):
        return final
    if final is None:
        try:
            metrics, y, batch = _evaluate(hybrid, problem, sim)
        except TrainingDiverged as exc:
            return exc
    else:
        metrics, y = dict(final[0]), final[1]
        batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    for name, value in hybrid.estimates().items():
        metrics[f"estimate.{name}"] = value
    return TrainResult(
        val_rmse=metrics["val.rmse"],
        metrics=metrics,
        history=mem.history,
        artifacts=artifacts_of(hybrid, metrics),
        figures=fit_figures(problem, batch, y, ref) if figures else {},
        hybrid=hybrid,
    )
