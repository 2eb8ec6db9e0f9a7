"""One Pareto front per kept equation, and a first choice on each.

The back end's front is joined by the scaled variants of its formulas
(:mod:`physmend.symbolic.scaled`) and, where formulas are chosen by the recordings, by the mechanism
catalogue's forms fitted to the target. A kept equation whose state is measured (its recorded
mismatch in ``rates``) takes the formula with the lowest BIC there
(:func:`~physmend.symbolic.choice.choose_by_recordings`); any other the front's rule (or the
engineer's index).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from physmend.symbolic.choice import catalogue_candidates, choose_by_recordings
from physmend.symbolic.scaled import scaled_variants
from physmend.symbolic.targets import RegressionData, equation_unit


@dataclass
class Fronts:
    """The fronts (``state -> ParetoFront``), the pick on each (``state -> (index, why)``) and,
    for the equations chosen by the recordings, ``(α, R²)`` per candidate against the recorded
    mismatch (``state -> list``)."""

    fronts: dict[str, Any] = field(default_factory=dict)
    picks: dict[str, tuple[int, str]] = field(default_factory=dict)
    recorded_scores: dict[str, list[tuple[float, float]]] = field(default_factory=dict)


def equation_fronts(problem: Any, data: RegressionData, kept: list[str], scale: list[str], sc: Any, *,
                    select: str, rates: Any, choices: dict[str, Any], operators: dict[str, Any] | None,
                    seed: int) -> Fronts:
    """A front per state of ``kept`` from the back end ``sc.backend`` (``sc.options``, ``sc.units``)
    on ``data``, widened and picked from as the module says; formulas left out for their units are
    said in one line each. ``choices``: the engineer's Pareto index per state (``symbolic.choice``)."""
    from physmend.symbolic import choose, fit_many

    out = Fronts()
    x_names, columns, units = data.x_names, data.columns, data.units
    # every equation's search (side by side where the back end allows: fit_many), then each in turn
    found = fit_many([dict(X=data.X, y=data.y[state], names=x_names, backend=str(sc.backend), target=state, units=units,
                           options=dict(sc.options or {}), seed=seed, operators=operators,
                           target_unit=equation_unit(problem.model, state, getattr(problem, "time_unit", "s")),
                           check_units=sc.units) for state in kept])
    for state, front in zip(kept, found):
        if front.info.get("unit_rejected"):
            print(f"{state}: {front.info['unit_rejected']} formula(s) left out, their units cannot be the equation's "
                  f"(e.g. {front.info['unit_rejected_examples'][0]})")
        if front.info.get("interval_rejected"):
            print(f"{state}: {front.info['interval_rejected']} formula(s) left out, they use a quantity on a scale with "
                  f"an offset (°C, °F) other than as a difference (e.g. {front.info['interval_rejected_examples'][0]})")
        extra = scaled_variants(front.candidates, scale, columns, data.y[state], operators=operators, units=units)
        if select == "recorded":
            extra += catalogue_candidates([*x_names, *scale], units, columns, data.y[state], operators=operators,
                                          scale_only=set(scale))
        if extra:
            front.candidates = sorted(front.candidates + extra, key=lambda c: (c.complexity, c.mse))
        out.fronts[state] = front
        if rates is not None and state in rates.targets and choices.get(state) is None:
            i, why, out.recorded_scores[state] = choose_by_recordings(rates, state, front)
            out.picks[state] = (i, why)
        else:
            out.picks[state] = choose(front, rule=str(sc.rule), index=choices.get(state))
    return out
