"""From a trained hybrid to the corrected model's formulas, end to end (the symbolic stage's work).

For every kept equation the target is the correction in the units of that equation's terms
(:mod:`physmend.symbolic.targets`). A back end returns a Pareto front (accuracy vs complexity); one
formula per equation is chosen by a stated rule (or by index), its numeric constants are named, and
they are re-fitted by simulating the corrected model (multiple shooting, no network:
Levenberg–Marquardt on the constants and the segment starts, :mod:`physmend.symbolic.refit`; the
model's own parameters stay as written, so the re-fitted model is exactly the one proposed). The
re-fit is kept only where it lowers the validation RMSE of whole-trajectory simulations; the
corrected model is simulated once with the regression's constants (which also checks that it can
be simulated at all) and once with the re-fitted ones.

With ``select="recorded"``, for every kept equation whose state is measured, the front is joined by
the mechanism catalogue's forms (each fitted to the target), and the formula is chosen by the
*recordings* rather than by the network: each candidate is scored against the measured equation's
mismatch along the forced trajectories (:mod:`physmend.ude.rates`), and the one with the lowest BIC
there (constants against independent windows) is taken. A network absorbs offsets and leans on
look-alike inputs; a formula that merely copies those quirks explains the recordings no better than
the simple form behind them. A kept equation whose state is not measured has no recorded mismatch:
its formula is chosen by the corrected model's fit of the training records
(:func:`~physmend.symbolic.simulated.choose_unmeasured`), and then each measured kept equation's
formula is weighed against none (:func:`~physmend.symbolic.simulated.drop_needless`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from physmend.settings import SymbolicSettings
from physmend.symbolic._errors import SymbolicError
from physmend.symbolic.correction import correction_for
from physmend.symbolic.corrected import corrected_metrics, corrected_problem, recalibratable, refit, simulate_corrected, with_parameters
from physmend.symbolic.fronts import equation_fronts
from physmend.symbolic.simulated import choose_on_short_record, choose_unmeasured, drop_needless
from physmend.symbolic.estimates import estimate_shifts, uncertainty_note
from physmend.symbolic.targets import regression_data


@dataclass
class Formulas:
    """What the symbolic stage found.

    ``kept``: the corrected equations (those whose formula buys too little dropped); ``x_names``: the
    regression's variables; ``fronts``/``chosen``: the Pareto front and the choice (index, why,
    expressions, unit) per kept state; ``recorded_scores``: ``(α, R²)`` per candidate against the
    recorded mismatch, where that chose; ``corrections``: the chosen formulas
    (:class:`~physmend.modeling.Correction`, constants possibly re-fitted); ``metrics``: the
    corrected model's ``train.rmse``/``val.rmse`` …; ``refit_note``: what the re-fit did (one
    sentence); ``recalibrated``: declared-uncertain parameter -> value re-fitted with the formulas;
    ``uncertainty``: re-fitted constant -> value, standard error, pinned down?; ``fallback``: the
    steps along a front a failing corrected model forced; ``shifts``: the jointly estimated
    parameters' moves (:func:`~physmend.symbolic.estimates.estimate_shifts`); ``declared``: the model's
    declared parameter values."""

    kept: list[str]
    x_names: list[str]
    fronts: dict[str, Any]
    chosen: dict[str, dict[str, Any]]
    recorded_scores: dict[str, list[tuple[float, float]]]
    corrections: list[Any]
    metrics: dict[str, float]
    refit_note: str
    recalibrated: dict[str, float]
    uncertainty: dict[str, dict[str, Any]]
    fallback: str
    shifts: list[str]
    declared: dict[str, float]


def find_formulas(hybrid: Any, problem: Any, work: Any, sc: Any, traj: Any, *, kept: list[str], inputs: list[str],
                  parameters: list[str], scale: list[str], choices: dict[str, Any], select: str,
                  operators: dict[str, Any] | None, seed: int) -> Formulas:
    """Formulas for the corrections ``kept`` of ``hybrid`` (trained on ``problem``; ``traj``: its
    training trajectories, :func:`physmend.ude.analysis.training_trajectories`), chosen and re-fitted
    as the module says.

    ``work``: the resolved configuration (times resolved); ``sc``: the ``symbolic`` settings (:class:`physmend.settings.SymbolicSettings`);
    ``inputs``: the network inputs passed on by the sensitivity run; ``parameters``: model
    parameters that are variables of the formulas; ``scale``: parameters that only scale a form;
    ``choices``: the engineer's Pareto index per kept state; ``select``: ``"recorded"`` or
    ``"rule"``; ``operators``: the configured operators (None: the back end's own).
    Raises :class:`SymbolicError` when no formula on the fronts gives a corrected model that can be
    simulated."""
    from physmend.modeling.corrections import constant_parameter_name
    from physmend.ude.metrics import checkpoint_problem

    data = regression_data(hybrid, problem, traj, kept, inputs, parameters, scale)
    columns, units = data.columns, data.units
    rates = None
    window = float(SymbolicSettings.build(work.symbolic).window)  # 'auto' resolved from the sampling interval (physmend.ude.timescale)
    if select == "recorded":
        from physmend.ude.rates import recorded_rates

        rates = recorded_rates(hybrid, problem, work, kept, float(window), traj.handed)
    # a kept equation whose state is not measured has no recorded mismatch: the simulated model decides
    simulated = [s for s in kept if select == "recorded" and choices.get(s) is None
                 and (rates is None or s not in rates.targets)]
    if operators is not None:  # sin/cos only where some input is an angle (physmend.symbolic.operators)
        from physmend.symbolic.operators import operators_for

        operators = operators_for(operators, {n: units[n] for n in data.x_names})
    found = equation_fronts(problem, data, kept, scale, sc, select=select, rates=rates, choices=choices,
                            operators=operators, seed=seed)
    # a long front's screening starts each candidate from the trained network's states (guide)
    choose_unmeasured(work, problem, simulated, found, data, sc, guide=hybrid)
    choose_on_short_record(work, problem, kept, found, data, rates, operators, sc, guide=hybrid)
    picks = found.picks
    dropped = drop_needless(work, problem, kept, simulated, choices, found.fronts, picks, columns, units, sc)
    kept = [s for s in kept if s not in dropped]
    fronts = {s: f for s, f in found.fronts.items() if s not in dropped}
    chosen: dict[str, dict[str, Any]] = {}
    fallback = ""
    while True:
        corrections = [correction_for(problem, state, fronts[state], *picks[state], columns, units, sc, chosen)
                       for state in kept]
        # every choice below sees training and validation data only
        corrected = checkpoint_problem(corrected_problem(work, corrections))
        ref, trouble = simulate_corrected(corrected, work)
        if trouble is None:
            break
        movable = [s for s in kept if picks[s][0] > 0 and s not in choices]
        if not movable:
            raise SymbolicError(f"the corrected model cannot be simulated with any formula on the fronts: {trouble}")
        worst = max(movable, key=lambda s: fronts[s].candidates[picks[s][0]].complexity)
        i = picks[worst][0] - 1
        fallback += f" Formula {picks[worst][0]} for {worst} made the corrected model fail ({trouble}); fell back to {i}."
        picks[worst] = (i, f"Fallback along the front to index {i} (a more complex formula made the corrected model unstable).")
    metrics = before = corrected_metrics(corrected, ref)
    uncertainty: dict[str, dict[str, Any]] = {}  # re-fitted constant -> value, standard error, pinned down?
    recalibrated: dict[str, float] = {}  # declared-uncertain parameter -> value re-fitted with the formulas
    iterations = int(sc.refit_epochs)
    refit_note = "constants as found by the regression (symbolic.refit_epochs=0)"
    recal = recalibratable(corrected, corrections, work) if sc.recalibrate else []
    for together in ([recal, []] if recal else [[]]) if iterations > 0 else []:
        fitted, result = refit(work, corrected, ref, corrections, iterations, recalibrate=together)
        values = {constant_parameter_name(corrected.model.owner.get(c.state, ""), c.state, k): v
                  for c in fitted for k, v in c.constants.items()} | {n: result.constants[n] for n in together}
        refitted = with_parameters(corrected, values)
        ref_after, trouble = simulate_corrected(refitted, work)
        after = corrected_metrics(refitted, ref_after) if ref_after is not None else {"val.rmse": float("inf")}
        what = "constants" + (f" and the declared-uncertain parameters {', '.join(together)}" if together else "")
        how = (f"{result.iterations} Levenberg–Marquardt step(s) on the multiple-shooting loss "
               f"{result.loss_before:.4g} → {result.loss_after:.4g}"
               + ("" if result.converged else f", stopped at symbolic.refit_epochs={iterations} before converging"))
        if after["val.rmse"] < before["val.rmse"]:
            corrections, metrics = fitted, after
            recalibrated = {n: result.constants[n] for n in together}
            refit_note = (f"{what} re-fitted through the simulator ({how}; validation RMSE "
                          f"{before['val.rmse']:.4g} → {after['val.rmse']:.4g})" + uncertainty_note(result))
            uncertainty = {k: {"value": result.constants[k], "stderr": result.stderr.get(k, math.inf),
                               "pinned": result.pinned(k)} for k in result.constants}
            break
        if ref_after is None:
            refit_note = (f"the {what} re-fitted through the simulator ({how}) made the corrected model fail "
                          f"({trouble}); the regression's constants are kept")
        else:
            refit_note = (f"re-fitting the {what} through the simulator ({how}) did not improve the validation RMSE "
                          f"({before['val.rmse']:.4g} → {after['val.rmse']:.4g}); the regression's constants are kept")
    return Formulas(kept=kept, x_names=data.x_names, fronts=fronts, chosen=chosen,
                    recorded_scores=found.recorded_scores, corrections=corrections, metrics=metrics,
                    refit_note=refit_note, recalibrated=recalibrated, uncertainty=uncertainty, fallback=fallback,
                    shifts=estimate_shifts(hybrid, problem, traj.handed),
                    declared={v.name: float(v.value) for v in problem.model.parameters})
