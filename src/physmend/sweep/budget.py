"""A sweep sized by its cost, not by a count: ``sweep.budget``.

With ``sweep.budget`` (seconds of wall time for the sweep's trials: a compute budget, not a
physical time of the model), the sweep first runs ``sweep.n_trials`` trials (the minimum), then
decides once how many trials the study has in the end. Trials run ``c`` at a time (a stack of
``sweep.group`` trials trained together, ``sweep.workers`` processes side by side), so more trials
come in rounds of ``c``, each costing what ``c`` of the first ones did:

    total = clamp(done + c · floor((budget - spent) / (c · spent / done)), n_trials, max_trials)

where ``done`` trials reached a verdict and ``spent`` is their wall-time span in the study storage
(first start to last end: trials that ran together overlap, so two side by side cost what they
took, not twice that). ``c`` is measured, not configured: the trials' summed durations over their
span, to the nearest whole number (1 where they ran one after another; then the rule is
``done + floor((budget - spent) / (spent / done))``). Where a trial takes seconds the sweep searches
more architectures; where the minimum alone takes longer than the budget it stays at the minimum.

Where each trial trains alone (``sweep.group: 1``) the minimum is proposed when the study is
created, as one group of ``n_trials`` would be (:func:`physmend.sweep.storage._study`), so the
trials measured are the same however many workers run them.

The decision is made once per study and stored with it (:data:`BUDGET_ATTR`): a resumed sweep,
and every worker of a study, use the same count. A worker whose trials of the minimum end before
the others' waits for the decision (:meth:`physmend.sweep.loop.Sweep.loop`), so that the trials it
allows run side by side in every worker, as the rule counts them, not in the last worker alone.

Run by one worker, the trials are deterministic given the count (each trial's sampler is seeded by
``seed`` + its number), so the same configuration, seed and count give the same trials; rerunning
with ``sweep.n_trials=<count> sweep.budget=null sweep.workers=1`` reproduces a budgeted sweep
anywhere. Run side by side, a trial after the minimum is proposed (once the sampler models the
space) and judged by the pruner against the trials finished when it asks and reports, which
depends on their timing, as in any parallel Optuna study; the minimum's trials are the same however
many workers run them. **The count itself depends on how fast this machine trains the first
trials**: it may differ between machines, and on one machine where the estimate falls near a
whole number of trials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from typing import Any

BUDGET_ATTR = "physmend_budget"
"""Study user attribute: the budget's decision, ``{"budget": s, "min": n, "max": n, "trials": n,
"spent": s, "measured": n, "at_once": c}``."""


@dataclass(frozen=True)
class Budget:
    """``seconds`` of wall time for a sweep of at least ``min_trials`` and at most ``max_trials`` trials."""

    seconds: float
    min_trials: int
    max_trials: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise ValueError(f"a budget must be a finite number of seconds > 0, but got {self.seconds!r}")
        if not 1 <= self.min_trials <= self.max_trials:
            raise ValueError(f"`1 <= min_trials <= max_trials` must hold, but got (min_trials={self.min_trials}, "
                             f"max_trials={self.max_trials})")

    def trials(self, spent: float, done: int, at_once: int = 1) -> int:
        """The study's total number of trials, after ``done`` trials took ``spent`` seconds of wall time
        running ``at_once`` at a time: as many more rounds of ``at_once`` as fit in what is left of the
        budget at ``at_once · spent / done`` seconds a round, within ``[min_trials, max_trials]``."""
        if done <= 0:
            return self.min_trials
        c = max(1, min(int(at_once), done))
        round_cost = c * max(spent, 0.0) / done
        left = self.seconds - max(spent, 0.0)
        more = self.max_trials if round_cost <= 0 else c * max(0, math.floor(left / round_cost))
        return max(self.min_trials, min(self.max_trials, done + more))

    def decision(self, spent: float, done: int, at_once: int = 1) -> dict[str, Any]:
        """What is stored with the study (:data:`BUDGET_ATTR`)."""
        return {"budget": self.seconds, "min": self.min_trials, "max": self.max_trials,
                "trials": self.trials(spent, done, at_once), "spent": round(float(spent), 3), "measured": int(done),
                "at_once": max(1, min(int(at_once), max(int(done), 1)))}

    def matches(self, stored: Any) -> bool:
        """Whether a stored decision was made for this budget (same seconds and bounds)."""
        return (isinstance(stored, dict) and stored.get("budget") == self.seconds and stored.get("min") == self.min_trials
                and stored.get("max") == self.max_trials and isinstance(stored.get("trials"), int))

    def describe(self, stored: dict[str, Any]) -> str:
        """One line: the decision and how it was reached."""
        done, spent, n = stored["measured"], stored["spent"], stored["trials"]
        each = spent / done if done else float("nan")
        c = stored.get("at_once", 1)
        pace = f", {c} at a time" if isinstance(c, int) and c > 1 else ""
        why = ("the budget allows no more" if n == self.min_trials and n < self.max_trials
               else "the most allowed (sweep.max_trials)" if n == self.max_trials else "as many as fit")
        return (f"budget {self.seconds:g} s: the first {done} trial{'s' if done != 1 else ''} took {spent:.1f} s "
                f"({each:.1f} s each{pace}), so {n} trial{'s' if n != 1 else ''} in all ({why}; at least {self.min_trials}, at most "
                f"{self.max_trials}); the count depends on this machine's speed — `sweep.n_trials={n} sweep.budget=null` "
                f"runs that many anywhere (with `sweep.workers=1`, the same trials)")


def wall_span(trials: list[Any]) -> float:
    """Seconds from the first start to the last end of the finished ``trials`` (Optuna ``FrozenTrial``s
    with ``datetime_start``/``datetime_complete``); 0 when none has both."""
    starts = [t.datetime_start for t in trials if isinstance(t.datetime_start, datetime)]
    ends = [t.datetime_complete for t in trials if isinstance(t.datetime_complete, datetime)]
    if not starts or not ends:
        return 0.0
    return max(0.0, (max(ends) - min(starts)).total_seconds())


def at_once(trials: list[Any]) -> int:
    """How many of the finished ``trials`` ran at a time: their summed durations over their
    :func:`wall_span`, to the nearest whole number (1 where they ran one after another or cannot tell)."""
    span = wall_span(trials)
    spans = [(t.datetime_complete - t.datetime_start).total_seconds() for t in trials
             if isinstance(t.datetime_start, datetime) and isinstance(t.datetime_complete, datetime)]
    if span <= 0 or not spans:
        return 1
    return max(1, min(len(spans), math.floor(sum(max(0.0, s) for s in spans) / span + 0.5)))
