"""The optimiser's schedule: the learning-rate multiplier per epoch (``train.schedule``, the
warm-up ramp after a warm start), the learning rate of every epoch for a stack member, and how
the rules of restarts (``train.restarts``: :func:`stops_at`) and patience (``train.patience_fit_gain``:
:func:`fit_progressed`). Every setting comes checked (:class:`physmend.settings.TrainSettings`).
"""

from __future__ import annotations

from collections.abc import Callable
import math

import torch

from physmend.settings import TrainSettings


def lr_factor(tc: TrainSettings, epochs: int, *, warm: bool) -> Callable[[int], float]:
    """Learning-rate multiplier per epoch: ``train.schedule`` (cosine | none), after a warm start
    ramped up linearly over ``train.warmup_epochs`` so the first steps do not undo it."""
    schedule = tc.schedule
    ramp = max(0, tc.warmup_epochs) if warm else 0

    def factor(epoch: int) -> float:
        f = 0.5 * (1 + math.cos(math.pi * min(epoch, epochs) / max(epochs, 1))) if schedule == "cosine" else 1.0
        return f * min(1.0, (epoch + 1) / ramp) if ramp else f

    return factor


def fit_progressed(train_rmse: float, best_fit: float | None, gain: float) -> tuple[bool, float]:
    """``(progressed, best)``: whether a checkpoint's whole-trajectory training RMSE is below
    ``(1 − gain)`` times the best so far (``best_fit``; None: none yet) with ``gain > 0``, and the
    best training RMSE including this one. While the fit still improves, patience waits even where
    the validation RMSE has not improved (a network leaving its warm start often fits the
    validation record worse for a while before it fits everything better; the best checkpoint is
    still the one that validates best)."""
    progressed = gain > 0 and best_fit is not None and math.isfinite(train_rmse) and train_rmse < (1.0 - gain) * best_fit
    return progressed, train_rmse if best_fit is None else min(best_fit, train_rmse)


def cycle_of(epoch: int, epochs: int) -> int:
    """The cycle (0: the first) that epoch ``epoch`` (1-based; 0: the warm start) belongs to."""
    return max(0, epoch - 1) // max(epochs, 1)


def stops_at(epoch: int, epochs: int, good_cycle: int | None) -> bool:
    """True when training stops before epoch ``epoch``: at the end of a cycle, once the model had a
    good checkpoint (one whose whole trajectories could be simulated) in the first cycle or in a
    cycle before the one that just ended. A model whose first good checkpoint came in a restarted
    cycle gets one more full cycle (it had only just begun to fit); one with none goes on."""
    if epoch <= epochs or (epoch - 1) % epochs != 0 or good_cycle is None:
        return False
    ended = cycle_of(epoch - 1, epochs)
    return good_cycle == 0 or good_cycle < ended


def lr_schedule(tc: TrainSettings, *, warm: bool) -> list[float]:
    """The learning rate of every epoch, from the optimiser/scheduler pair train() uses."""
    epochs = tc.epochs
    dummy = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([dummy], lr=float(tc.lr))
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor(tc, epochs, warm=warm))
    lrs = []
    for _ in range(epochs):
        lrs.append(float(opt.param_groups[0]["lr"]))
        opt.step()  # no gradient: nothing moves; keeps the scheduler's step-order check quiet
        sched.step()
    return lrs
