"""What training returns: a model's :class:`TrainResult`, or :class:`TrainingDiverged`. Imports ``hybrid``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from physmend.exceptions import PhysmendError
from physmend.ude.hybrid import HybridModel


class TrainingDiverged(PhysmendError, RuntimeError):
    """Training produced non-finite losses or trajectories; the message says when and why."""


@dataclass
class TrainResult:
    """Outcome of one training run (see :func:`train`)."""

    val_rmse: float
    metrics: dict[str, float]
    history: list[dict[str, float]]
    artifacts: dict[str, str | bytes]
    figures: dict[str, Any] = field(default_factory=dict)
    hybrid: HybridModel | None = None

    def on_cpu(self) -> TrainResult:
        """This result with its model moved to the CPU (a training on a GPU returns it so: every
        other stage works on the CPU). On the CPU already: itself, unchanged."""
        hybrid = self.hybrid
        if hybrid is not None and hybrid.mean.device.type != "cpu":
            hybrid.to("cpu")
            hybrid.initial_estimates = {k: v.cpu() for k, v in hybrid.initial_estimates.items()}
        return self
