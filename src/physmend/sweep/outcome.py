"""How one trial of a sweep ended: :class:`Outcome`, what the study loop tells Optuna and counts."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Outcome:
    """How one trial ended."""

    number: int
    state: str  # COMPLETE | PRUNED | FAIL
    value: float | None = None
    run_id: str | None = None
    reason: str = ""
    restarts: int = 0  # trainings restarted after divergence (sweep.restarts)
