"""Choices made by simulating the corrected model (:func:`~physmend.symbolic.choice.choose_by_simulation`):
the formula of a kept equation whose state is not measured (no recorded mismatch exists for it), the
formula of a measured equation where a short record gives too few independent windows of recorded
mismatch to rank by, and measured equations whose correction the corrected model does not need."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import sympy as sp

from physmend.symbolic.choice import MIN_RECORDED_WINDOWS, choose_by_simulation
from physmend.symbolic.correction import correction_for
from physmend.symbolic.fronts import Fronts
from physmend.symbolic.targets import RegressionData

#: a short record's choice by simulation re-fits at most this many formulas: those the recorded
#: mismatch ranks best (a weak ranking on few windows, but one that costs nothing)
SHORTLIST = 16
#: ... joined by this many of the library's products and ratios of two variables (best fit of the target first)
LIBRARY_SHORTLIST = 6


def recorded_shortlist(front: Any, scores: list[tuple[float, float]], windows: float,
                       size: int = SHORTLIST) -> list[int]:
    """Indices of the ``size`` candidates of ``front`` with the lowest BIC against the recorded
    mismatch, ``n·ln(1 − R²) + k·ln(n)`` over ``n = windows`` (``scores``: ``(α, R²)`` per candidate)."""
    from physmend.modeling.evaluate import n_constants

    n = max(2.0, windows)

    def bic(i: int) -> float:
        r2 = scores[i][1]
        if not np.isfinite(r2):
            return math.inf
        return n * math.log(max(1.0 - r2, 1e-12)) + n_constants(front.candidates[i].expr) * math.log(n)

    return sorted(range(len(front.candidates)), key=bic)[:size]


def _steps(sc: Any) -> int:
    """Levenberg–Marquardt steps at most per candidate of a choice by simulation (a screened front's
    finalists): as many as the chosen formula's re-fit (``symbolic.refit_epochs``), so that candidates
    are compared at the losses they converge to — ten steps left a constant behind forms with two
    that moved their segment starts faster, and chose a worse formula on held-out data."""
    return int(sc.refit_epochs)


def choose_unmeasured(work: Any, problem: Any, simulated: list[str], found: Fronts, data: RegressionData,
                      sc: Any, guide: Any = None) -> None:
    """Pick (in ``found.picks``) the formula of each state of ``simulated`` (kept, not measured):
    each is judged in the corrected model with the other unmeasured ones' formulas; the measured
    equations' corrections come after (:func:`drop_needless`): a network may have split one term
    between them. ``guide``: the trained hybrid, whose states start every candidate's segments."""
    fronts, picks = found.fronts, found.picks
    for state in simulated:
        def build(i: int, state: str = state) -> list:
            return [correction_for(problem, s, fronts[s], *((i, "") if s == state else picks[s]), data.columns,
                                   data.units, sc, {}) for s in simulated]
        picks[state] = choose_by_simulation(work, problem, state, fronts[state], build, _steps(sc), guide=guide)


def choose_on_short_record(work: Any, problem: Any, kept: list[str], found: Fronts, data: RegressionData, rates: Any,
                           operators: dict[str, Any] | None, sc: Any, guide: Any = None) -> None:
    """Where the training records give fewer than :data:`~physmend.symbolic.choice.MIN_RECORDED_WINDOWS`
    independent windows of recorded mismatch (a handful of window means), re-pick (in ``found``) the
    formula of each measured kept equation by the corrected model's simulation of every training
    sample: among the :data:`SHORTLIST` the recorded mismatch ranks best and the library's products
    and ratios (:data:`LIBRARY_SHORTLIST`), which join its front."""
    from physmend.symbolic import ParetoFront
    from physmend.symbolic.choice import independent_windows
    from physmend.symbolic.library import pair_candidates

    fronts, picks, recorded_scores = found.fronts, found.picks, found.recorded_scores
    columns, units, x_names = data.columns, data.units, data.x_names
    windows = independent_windows(rates) if rates is not None else math.inf
    short = [s for s in kept if s in recorded_scores and windows < MIN_RECORDED_WINDOWS]
    for state in short:  # a short record: the recorded mismatch is a handful of window means; every sample decides
        front = fronts[state]
        names_lib = [n for n in x_names if n not in problem.model.parameter_names]
        lib = pair_candidates(names_lib, columns, data.y[state], operators=operators, units=units)
        scores = recorded_scores[state] + [(a, r2) for a, _, r2 in (rates.score(c.expr, state) for c in lib)]
        # the front stays sorted by complexity (the fallback below steps to simpler formulas); indices remapped
        merged_ = front.candidates + lib
        order = sorted(range(len(merged_)), key=lambda i: (merged_[i].complexity, merged_[i].mse))
        where = {old: new for new, old in enumerate(order)}
        front.candidates = [merged_[i] for i in order]
        recorded_scores[state] = [scores[i] for i in order]
        picks[state] = (where[picks[state][0]], picks[state][1])
        shortlist = recorded_shortlist(front, recorded_scores[state], windows)
        # the library's products and ratios are judged by the simulation whatever a few window means say
        first_lib = len(merged_) - len(lib)
        shortlist += [where[first_lib + j] for j in range(min(LIBRARY_SHORTLIST, len(lib)))
                      if where[first_lib + j] not in shortlist]
        sub = ParetoFront(backend=front.backend, target=state, inputs=front.inputs,
                          candidates=[front.candidates[i] for i in shortlist])

        def build_all(i: int, state: str = state, shortlist: list[int] = shortlist) -> list:
            return [correction_for(problem, s, fronts[s], *((shortlist[i], "") if s == state else picks[s]), columns,
                                   units, sc, {}) for s in kept]
        i, why = choose_by_simulation(
            work, problem, state, sub, build_all, _steps(sc),
            reason=(f"the training records give only {windows:.0f} independent windows of recorded mismatch, fewer "
                    f"than {MIN_RECORDED_WINDOWS}: the formulas they rank best and the library's products and ratios, "
                    f"{len(shortlist)} in all, are put into the model, whose simulation of every training sample "
                    "decides"), guide=guide)
        if why.startswith("Rule 'simulated': no formula"):  # none could be solved: the recorded choice stands
            continue
        picks[state] = (shortlist[i], why.replace(f"chose index {i} (", f"chose index {shortlist[i]} ("))


def drop_needless(work: Any, problem: Any, kept: list[str], simulated: list[str], choices: dict, fronts: dict,
                  picks: dict, columns: dict, units: dict, sc: Any) -> dict[str, str]:
    """Measured equations whose correction the corrected model does not need, once the unmeasured
    ones (``simulated``) carry their formulas: ``{state: why}``.

    A network may split one missing term between an unmeasured state's equation and the measured
    equation downstream of it (the mask keeps both when they validate alike). With the unmeasured
    equation's formula in the model, each measured equation's chosen formula is weighed against
    none at all by the same rule (:func:`choose_by_simulation`: constants re-fitted, BIC of the
    simulated training records); a formula that buys too little is dropped.
    """
    from physmend.symbolic import Candidate, ParetoFront

    out: dict[str, str] = {}
    if not simulated:
        return out
    for state in [s for s in kept if s not in simulated and choices.get(s) is None]:
        chosen = fronts[state].candidates[picks[state][0]]
        none = Candidate(expr=sp.Integer(0), complexity=0, mse=float("nan"), r2=0.0, text="no correction")
        pair = ParetoFront(backend=fronts[state].backend, target=state, inputs=fronts[state].inputs,
                           candidates=[none, chosen])

        def build(i: int, state: str = state) -> list:
            return [correction_for(problem, s, fronts[s], *picks[s], columns, units, sc, {})
                    for s in kept if s not in out and (s != state or i == 1)]

        i, why = choose_by_simulation(work, problem, state, pair, build, _steps(sc))
        if i == 0:
            out[state] = why
            print(f"{state}: no correction — with the formulas of {', '.join(simulated)} in the model, its chosen "
                  f"formula ({chosen.text}) does not pay for its constants in the simulated training records.")
    return out
