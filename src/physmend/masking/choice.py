"""Which corrections to keep: the smallest k of the ranking whose masked network validates within a
tolerance of the full one (:func:`choose_k`), the other equation sets worth retraining
(:func:`rivals`), and the set whose retrained network validates best (:func:`best_retrained`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


def choose_k(full: float, by_k: list[tuple[int, float]], tolerance: float) -> int:
    """The smallest k with ``rmse_k <= (1 + tolerance) * full``.

    When no k qualifies (the network spread small corrections over many equations, so every
    masked version loses some fit — the retraining restores it), the smallest k within the same
    tolerance of the best masked RMSE: more corrections that barely help are not kept.
    """
    for k, rmse in by_k:
        if rmse <= (1.0 + tolerance) * full:
            return k
    best = min(r for _, r in by_k)
    return next(k for k, r in by_k if r <= (1.0 + tolerance) * best)


def rivals(kept: list[str], order: list[str], n: int, measured: set[str] | None = None) -> list[list[str]]:
    """Other equation sets worth retraining: the last kept equation swapped for each of the next
    ``n`` in the ranking ``order``. With ``measured`` (states that are outputs), only when the last
    kept state is measured, and only unmeasured rivals: the ranking is biased exactly there (a
    warm start fits measured equations; a hidden state's correction hides behind them). And a kept
    set that mixes measured and unmeasured states has the unmeasured ones alone and the measured
    ones alone as rivals: one side's correction may be the shadow of the other's (the two-tank
    network put 96% of an upper tank's leak on the measured lower tank, the upper tank's equation
    retrained alone validated 2.5x better than both; a drug's elimination from the measured plasma
    can be spread onto the hidden tissue compartment)."""
    if n <= 0 or not kept:
        return []
    sets: list[list[str]] = []
    if measured is not None:
        hidden = [name for name in kept if name not in measured]
        if hidden and len(hidden) < len(kept):  # either side alone: one term may be split between them
            sets += [hidden, [name for name in kept if name in measured]]
    others = [o for o in order if o not in kept]
    if measured is not None:
        if kept[-1] not in measured:
            return sets
        others = [o for o in others if o not in measured]
    return sets + [kept[:-1] + [name] for name in others[:n] if kept[:-1] + [name] not in sets]


@dataclass
class SourceNetwork:
    """The mask's source network standing for a retraining of its own equation set (``val_rmse``:
    its validation RMSE): that retraining would reproduce it."""

    val_rmse: float


def val_rmse(result: Any) -> float:
    """A candidate's validation RMSE (NaN for a retraining that failed: an exception)."""
    return float("nan") if isinstance(result, Exception) else float(result.val_rmse)


def val_text(result: Any) -> str:
    """A candidate's validation RMSE for the printout; where it has none, why (the error, one line)."""
    if isinstance(result, Exception):
        from physmend.sweep.restart import one_line

        return f"nan ({one_line(result)})"
    return f"{val_rmse(result):.4g}"


def best_retrained(tried: list[tuple[list[str], Any]], tolerance: float = 0.0) -> tuple[list[str], Any]:
    """The equation set whose retrained network validates best (training and validation experiments
    only) — or a smaller set whose validation RMSE is within ``(1 + tolerance)`` of that best (fewest
    equations first, then the lowest RMSE): the same rule as the choice of k. The first set's error
    when every one diverged."""
    ok = [(names, r) for names, r in tried if not isinstance(r, Exception) and math.isfinite(r.val_rmse)]
    if not ok:
        raise tried[0][1]
    best = min(r.val_rmse for _, r in ok)
    near = [(names, r) for names, r in ok if r.val_rmse <= (1.0 + tolerance) * best]
    return min(near, key=lambda item: (len(item[0]), item[1].val_rmse))
