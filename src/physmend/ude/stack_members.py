"""Each member of a stack prepared (its hybrid, optimiser settings, segment starts) and the shared
batched warm start. Imports ``hybrid``, ``stack``, ``reference``, ``shooting``, ``spec``,
``schedule``, ``warmstart``.
"""

from __future__ import annotations

from omegaconf import DictConfig
import torch

from physmend.problem import Problem
from physmend.ude.hybrid import HybridModel, UDEConfigError
from physmend.ude.stack import _Member, _Stack
from physmend.ude.reference import Reference
from physmend.ude.schedule import _chain, _lr_schedule
from physmend.ude.shooting import Shooting, initial_segments, chained_starts
from physmend.ude.spec import build_spec
from physmend.ude.warmstart import Forced, forced_trajectories, recall, remember, segment_starts, warm_key, warm_start


def _prepare(cfg: DictConfig, problem: Problem, ref: Reference, plan: Shooting, slot: int, *, warm: bool = True) -> _Member:
    """One model exactly as train() starts it: seed, spec, network, warm start (``warm``; otherwise
    the stack does it, batched), segment starts."""
    torch.manual_seed(int(cfg.get("seed", 0)))
    spec = build_spec(cfg, problem, ref)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    seg0 = initial_segments(problem, ref, plan)
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
