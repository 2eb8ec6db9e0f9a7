"""Each member of a stack prepared (its hybrid, optimiser settings, segment starts) and the shared
batched warm start. Imports ``hybrid``, ``stack``, ``reference``, ``shooting``, ``spec``,
``schedule``, ``warmstart``.
"""

from __future__ import annotations

from typing import Any

import torch

from physmend.problem import Problem
from physmend.settings import TrainingSettings
from physmend.ude.checkpoints import Checkpoints
from physmend.ude.hybrid import HybridModel, UDEConfigError
from physmend.ude.stack.solve import Member, Stack
from physmend.ude.reference import Reference
from physmend.ude.schedule import lr_schedule
from physmend.ude.shooting import BOX_MARGIN, Shooting, chained_starts, initial_segments, pinned_starts, segments_finite
from physmend.ude.spec import build_spec
from physmend.ude.warmstart import (Forced, forced_trajectories, recall, remember, same_warm_start, segment_starts, warm_key,
                                    warm_start)


def prepare(cfg: TrainingSettings, problem: Problem, ref: Reference, plan: Shooting, slot: int, *, warm: bool = True) -> Member:
    """One model exactly as train() starts it: seed, spec, network, warm start (``warm``; otherwise
    the stack does it, batched), segment starts."""
    torch.manual_seed(cfg.seed)
    spec = build_spec(cfg, problem, ref)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    seg0 = initial_segments(problem, ref, plan)
    chain = cfg.train.chained
    forced = warm_start(hybrid, problem, ref.batch, cfg) if warm else None
    if forced is not None:
        seg0 = segment_starts(forced, plan.exp_index, plan.starts, seg0)
        if chain:
            params_seg = ref.batch.params[plan.exp_index]
            u0 = torch.where(plan.first[:, None], ref.batch.u0[plan.exp_index], seg0)
            seg0 = chained_starts(hybrid.rhs(hybrid.parameters_for(params_seg)), u0, plan, keep=forced.measured)
    return Member(slot=slot, cfg=cfg, hybrid=hybrid, forced=forced, seg0=seg0,
                  lrs=lr_schedule(cfg.train, warm=forced is not None), marks=Checkpoints(cfg.train))


def warm_settings(cfg: TrainingSettings) -> tuple[str, int, int]:
    """``(train.warm_start, warm_iterations, window in grid steps)``: as :func:`warm_start` reads them."""
    tc = cfg.train
    return tc.warm_start, tc.warm_iterations, tc.warm_window_steps


def shared_warm_start(members: list[Member], problem: Problem, ref: Reference, plan: Shooting) -> tuple[Forced, int, int] | None:
    """The warm start every model asks for (``auto``, the same settings): the forced trajectories
    (computed once: they depend only on the records and the initial parameter estimates, which the
    stack shares), with each member's segment starts and schedule set as :func:`prepare` would;
    None where no output is a state (no warm start, as alone)."""
    _, iterations, window = warm_settings(members[0].cfg)
    forced = forced_trajectories(problem, ref.batch, members[0].hybrid, float(members[0].cfg.train.step))
    if forced is None:
        return None
    for mem in members:
        mem.forced = forced
        mem.seg0 = segment_starts(forced, plan.exp_index, plan.starts, mem.seg0)
        mem.lrs = lr_schedule(mem.cfg.train, warm=True)
    return forced, iterations, window


def warm_fit_members(members: list[Member], problem: Problem, ref: Reference, plan: Shooting, cfg: TrainingSettings,
              forced: Forced, iterations: int, window: int) -> None:
    """Every member's warm start: one batched regression of the models this process has not
    warm-started before (:func:`physmend.ude.warmstart.warm_key`: same network as initialised, data
    and settings); the others reuse the stored result, which is what the regression would give."""
    p_exp = ref.batch.params[forced.exp_index]
    keys = [warm_key(mem.hybrid, forced, p_exp, iterations, window) for mem in members]
    todo: dict[str, Member] = {}
    for mem, key in zip(members, keys):
        if key not in todo and not recall(key, mem.hybrid):
            todo[key] = mem
    if todo:
        sub = Stack(list(todo.values()), problem, ref, plan, cfg)
        sub.warm_fit(forced, iterations=iterations, window=window)
        for pos in range(sub.size):
            sub.write_back(pos)
        for key, mem in todo.items():
            remember(key, mem.hybrid)
    for mem, key in zip(members, keys):
        mem.warm_key = key
        if key in todo and todo[key] is not mem:
            recall(key, mem.hybrid)


def check_same_shape(members: list[Member]) -> None:
    a = members[0].hybrid.spec
    for mem in members[1:]:
        s = mem.hybrid.spec
        same = (s.corrected == a.corrected and s.input_names == a.input_names and s.estimated == a.estimated
                and s.mean == a.mean and s.std == a.std)
        if not same:
            raise UDEConfigError(f"train_stack: model {mem.slot} corrects or reads other variables than model "
                                 f"{members[0].slot} (ude.corrected / ude.inputs / train.estimate_parameters must agree)")


def drop_unstable_warm_starts(members: list[Member], initial: list[dict[str, Any]], ref: Reference,
                               plan: Shooting) -> None:
    """A member whose warm-started network leaves the finite range on its own segments goes back to
    its network as initialised and trains without a warm start (as :func:`train` does). Members of
    one warm start (the same network, starts and estimates: trials that differ in their training
    settings only) are checked once."""
    pinned, _, _ = pinned_starts(ref.batch, plan, members[0].hybrid.compiled.state_names)
    fixed_first = ref.batch.u0[plan.exp_index]
    params_seg = ref.batch.params[plan.exp_index]
    box = members[0].hybrid.spec.box(BOX_MARGIN, ref.batch.t.dtype)  # as the stack trains (states held in it)
    firsts = same_warm_start([mem.warm_key for mem in members])
    finite: list[bool] = []
    for i, (mem, state) in enumerate(zip(members, initial)):
        if firsts[i] == i:
            rhs = mem.hybrid.rhs(mem.hybrid.parameters_for(params_seg))
            finite.append(segments_finite(rhs, torch.where(pinned, fixed_first, mem.seg0), plan, box))
        else:
            finite.append(finite[firsts[i]])
        if not finite[i]:
            mem.hybrid.load_state_dict(state)
            mem.forced, mem.warm_key = None, None
            mem.lrs = lr_schedule(mem.cfg.train, warm=False)
