"""The reference simulation and the multiple-shooting plan of a stack, computed once per problem and
settings in a process, and the experiments grouped by their time grid. Imports ``reference``, ``shooting``.
"""

from __future__ import annotations

from typing import Any
import json

from omegaconf import DictConfig
import torch

from physmend.problem import Problem
from physmend.simulate import Batch, make_batch
from physmend.ude.reference import Reference, solver_options, reference
from physmend.ude.shooting import Shooting, plan_shooting


def plan_key(plan: Shooting) -> tuple[Any, ...]:
    """What identifies a shooting plan's segments (step, steps per segment, starts, experiments)."""
    return (plan.dt, plan.steps, tuple(plan.starts.tolist()), tuple(plan.exp_index.tolist()))


#: reference simulations and shooting plans of the last few problems this process trained on: every
#: stack of a sweep shares them (they depend on the problem and the solver and shooting settings only)
SETUPS: dict[int, tuple[Problem, dict[Any, Reference], dict[Any, Shooting]]] = {}

SETUPS_MAX = 4


def setup(problem: Problem, cfg: DictConfig, *, plan: bool = True) -> tuple[Reference, Shooting | None]:
    """``(reference(problem, cfg), plan_shooting(problem, ref.batch, cfg))``, computed once per
    problem, solver settings and shooting settings in this process (``plan=False``: no plan)."""
    entry = SETUPS.get(id(problem))
    if entry is None or entry[0] is not problem:
        if len(SETUPS) >= SETUPS_MAX:
            SETUPS.pop(next(iter(SETUPS)))
        entry = SETUPS[id(problem)] = (problem, {}, {})
    _, refs, plans = entry
    # a reference lives on one device (physmend.device): computed once per device
    ref_key = json.dumps([solver_options(cfg), str(torch.get_default_device())], sort_keys=True, default=str)
    ref = refs.get(ref_key)
    if ref is None:
        ref = refs[ref_key] = reference(problem, cfg, bounded=True)  # within the data where the model diverges
    if not plan:
        return ref, None
    plan_key = (ref_key, float(cfg.train.step), float(cfg.train.segment_length))
    shooting = plans.get(plan_key)
    if shooting is None:
        shooting = plans[plan_key] = plan_shooting(problem, ref.batch, cfg)
    return ref, shooting


def time_grid_parts(problem: Problem, batch: Batch) -> list[tuple[list[int], Batch, torch.Tensor | None]]:
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
