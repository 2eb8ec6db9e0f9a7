"""One model's checkpoints while it trains: the rules the single-model trainer
(:func:`physmend.ude.train.train`) and the stacked one (:func:`physmend.ude.stack.train_stack`)
share — which checkpoint is best, when patience runs out, when a cycle of epochs ends training and
when it restarts (``train.restarts``), which models are worth polishing with L-BFGS.

A checkpoint simulates whole trajectories; its row in :attr:`Checkpoints.history` holds the epoch,
the multiple-shooting loss and fit term at that epoch, and ``val.rmse``/``train.rmse`` (inf where the
simulation failed). Imports ``outcome``, ``polish``, ``schedule``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from physmend.settings import TrainSettings
from physmend.ude.outcome import TrainingDiverged
from physmend.ude.polish import fit_at, worth_polishing
from physmend.ude.schedule import cycle_of, fit_progressed, stops_at


def evaluation_due(epoch: int, tc: TrainSettings) -> bool:
    """Whether epoch ``epoch`` (1-based) ends with a checkpoint: every ``train.eval_every`` epochs and
    at the end of every cycle of ``train.epochs``."""
    return epoch % tc.eval_every == 0 or epoch % tc.epochs == 0


@dataclass
class Checkpoints:
    """The checkpoints of one model: its history, best state, patience and training cycle.

    Attributes:
        history: one row per checkpoint, in order.
        best: ``(val.rmse, state_dict, metrics)`` of the checkpoint with the lowest validation RMSE.
        since_best: checkpoints since the last progress (patience counts them).
        best_fit: the lowest whole-trajectory training RMSE so far (``train.patience_fit_gain``).
        good_cycle: the cycle (0: the first) of the first checkpoint that could be simulated.
        failed: the last checkpoint whose whole trajectory failed (its error).
    """

    settings: TrainSettings
    history: list[dict[str, float]] = field(default_factory=list)
    best: tuple[float, dict[str, Any], dict[str, float]] | None = None
    since_best: int = 0
    best_fit: float | None = None
    good_cycle: int | None = None
    failed: TrainingDiverged | None = None

    @property
    def patience_ran_out(self) -> bool:
        """``train.patience`` checkpoints in a row without progress (never with patience 0)."""
        patience = self.settings.patience
        return patience > 0 and self.since_best >= patience

    def diverged(self, epoch: int, loss: float, fit: float, error: TrainingDiverged) -> bool:
        """A checkpoint whose whole trajectory failed: not a candidate, but training goes on (the next
        may be fine); patience counts it. Returns True when patience has run out — only after a good
        checkpoint: a start that diverges (a warm start out of its data) is for training to repair."""
        self.failed = error
        self.history.append({"epoch": float(epoch), "loss": loss, "fit_loss": fit, "val.rmse": math.inf,
                             "train.rmse": math.inf})
        self.since_best += 1
        return self.best is not None and self.patience_ran_out

    def record(self, epoch: int, loss: float, fit: float, metrics: dict[str, float],
               state: Callable[[], dict[str, Any]]) -> dict[str, float]:
        """A checkpoint with whole-trajectory ``metrics``; ``state()`` gives the model's state to keep
        when it is the best so far. Returns its history row (what a ``report`` callback gets)."""
        row = {"epoch": float(epoch), "loss": loss, "fit_loss": fit,
               **{k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")}}
        self.history.append(row)
        if self.best is None:
            self.good_cycle = cycle_of(epoch, self.settings.epochs)
        fitting, self.best_fit = fit_progressed(metrics["train.rmse"], self.best_fit, self.settings.patience_fit_gain)
        if self.best is None or metrics["val.rmse"] < self.best[0]:
            self.best = (metrics["val.rmse"], state(), metrics)
            self.since_best = 0
        elif fitting:
            self.since_best = 0
        else:
            self.since_best += 1
        return row

    def stops_before(self, epoch: int) -> bool:
        """Whether training stops before epoch ``epoch`` at the end of a cycle (see :func:`stops_at`)."""
        return stops_at(epoch, self.settings.epochs, self.good_cycle)

    def worth_polishing(self, noise: float) -> bool:
        """Whether L-BFGS should polish from the best checkpoint (there is one, ``train.polish`` > 0,
        and its training fit is not at the sensor noise ``noise`` already)."""
        return (self.settings.polish_iterations > 0 and self.best is not None
                and worth_polishing(fit_at(self.history, self.best[0]), noise))

    def best_state(self) -> dict[str, Any]:
        """The best checkpoint's state; raises the last failure when every checkpoint failed."""
        if self.best is None:
            raise self.failed or TrainingDiverged("no checkpoint was evaluated")
        return self.best[1]

    @property
    def failures(self) -> float:
        """How many checkpoints could not be simulated (the ``checkpoints.failed`` metric)."""
        return float(sum(math.isinf(r["val.rmse"]) for r in self.history))


def last_epoch(histories: list[list[dict[str, float]]], default: int) -> int:
    """The epoch of the last checkpoint of any model (``default`` when there is none): polishing counts on from it."""
    return max((int(r["epoch"]) for h in histories for r in h), default=default)
