"""The model as written simulated on every experiment, and where it diverges.

A model as written that diverges — an output leaves the range of the records by more than
:data:`physmend.simulate.divergence.RANGE_MARGIN` ranges, or the model blows up in finite time —
is a finding, not a failure. A model that blows up is simulated held inside the box of its measured
states (:func:`physmend.simulate.divergence.projected`), so there is a table all the same.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from physmend.problem import Problem
from physmend.settings import SimulateSettings
from physmend.simulate import Batch, SimulationError, Trajectories, simulate_batch
from physmend.simulate.divergence import Divergence


def simulate_as_written(problem: Problem, batch: Batch, cfg: Any) -> tuple[Trajectories, list[Divergence]]:
    """The model as written on every experiment, and where it diverges (nothing written).

    Where the solve fails and the model can be held inside the box of its measured states
    (a finite-time blow-up), the held solve's trajectories; the failure is raised where it cannot,
    or where the held solve reaches no box (the failure is not a divergence)."""
    from physmend.ude.reference import find_divergence, output_boxes, state_boxes

    opts = SimulateSettings.build(cfg.simulate).solver()
    with torch.no_grad():
        try:
            traj = simulate_batch(problem.compiled, batch, **opts)
            return traj, find_divergence(problem, batch, traj.outputs)
        except SimulationError as exc:
            _, _, box_lo, box_hi = output_boxes(problem, batch)
            lo, hi = state_boxes(problem, batch, box_lo, box_hi)
            if not bool((torch.isfinite(lo) | torch.isfinite(hi)).any()):
                raise
            try:
                traj = simulate_batch(problem.compiled, batch, **opts, box=(lo, hi))
            except SimulationError:
                raise exc from None
            found = find_divergence(problem, batch, traj.outputs, blows_up=True)
            if not found:
                raise exc from None
            return traj, found


def json_ready(d: Divergence) -> dict[str, Any]:
    """``d`` as a dict for JSON: a non-finite number (a blow-up's infinite peak) becomes None."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.as_dict().items()}
