"""``physmend symbolic [RUN_ID]``: the network's corrections become formulas.

For every kept equation the target is the correction in the units of that equation's terms
(``a·ΔNN`` for an equation ``a·der(x) = …``: watts for a heat balance), so a formula need not
know capacities and generalises across configurations. Inputs: the inputs passed on by the
sensitivity run plus ``symbolic.parameters``. A back end returns a Pareto front (accuracy vs
complexity); one formula per equation is chosen by a stated rule (or by index), its numeric
constants are named, and they are re-fitted by simulating the corrected model (multiple
shooting, no network: Levenberg–Marquardt on the constants and the segment starts,
:mod:`physmend.symbolic.refit`; the model's own parameters stay as written, so the re-fitted
model is exactly the one proposed). The re-fit is kept only where it lowers the validation RMSE
of whole-trajectory simulations; the corrected model is simulated once with the regression's
constants (which also checks that it can be simulated at all) and once with the re-fitted ones.

With ``symbolic.select: recorded`` (default), for every kept equation whose state is measured, the front
is joined by the mechanism catalogue's forms (each fitted to the target), and the formula is
chosen by the *recordings* rather than by the network: each candidate is scored against the
measured equation's mismatch along the forced trajectories (:mod:`physmend.ude.rates`), and the
one with the lowest BIC there (constants against independent windows) is taken. A network
absorbs offsets and leans on look-alike inputs; a formula that merely copies those quirks explains
the recordings no better than the simple form behind them. A kept equation whose state is not
measured has no recorded mismatch: its formula is chosen by the corrected model's fit of the
training records (:func:`choose_by_simulation`), and then each measured kept equation's formula is
weighed against none (:func:`drop_needless`).
"""

from __future__ import annotations

import math

from typing import Any

import numpy as np
import sympy as sp
from omegaconf import OmegaConf
import torch

from physmend.symbolic.choice import (  # noqa: F401 - the stage's pieces, importable from here too
    SELECTION_REFIT_STEPS, catalogue_candidates, choose_by_recordings, choose_by_simulation, tree_size)
from physmend.symbolic.constants import identifiable, name_constants  # noqa: F401
from physmend.symbolic.corrected import (  # noqa: F401
    corrected_metrics, corrected_problem, recalibratable, refit, simulate_corrected, with_parameters)

STAGE = "symbolic"



def equation_unit(model: Any, state: str, time_unit: str = "s") -> str:
    """The unit of the terms of ``state``'s equation: for ``der(x) = …`` (coefficient 1) the rate
    ``unit(x)/time_unit``; otherwise the unit of a variable of its right-hand side whose dimension is
    the right-hand side's (a heat flow in a heat balance ``C·der(T) = P − UA·(T − T_room)``, not a
    temperature), the first such by name; the first variable's unit when the units cannot tell."""
    if model.der_coefficient.get(state, 1) == 1 and model.units.get(state):
        return f"{model.units[state]}/{time_unit}"
    eq = model.equations.get(state)
    if eq is None:
        return ""
    from physmend.modeling.units import ANY, UnitMismatch, dimension, formula_dimension, same

    labels = [model.units.get(sym.name, "") for sym in sorted(eq.rhs.free_symbols, key=lambda s: s.name)
              if sym.name not in model.parameter_names]
    labels = [u for u in labels if u]
    try:  # the right-hand side's dimension, from every declared unit (parameters' included)
        want = formula_dimension(eq.rhs, model.units)
    except UnitMismatch:
        want = ANY
    if want is not ANY:
        for unit in labels:
            d = dimension(unit)
            if d is not None and same(d, want):  # type: ignore[arg-type]
                return unit
    return labels[0] if labels else ""


def canonical_form(expr: sp.Expr, columns: dict[str, np.ndarray], units: dict[str, str], min_r2: float) -> tuple[sp.Expr, str, float] | None:
    """The mechanism catalogue's clean form of ``expr`` (one constant) if it reproduces ``expr``
    on the samples with R² ≥ ``min_r2``; ``None`` otherwise."""
    from physmend.explain.mechanisms import classify, load_catalogue

    used = {s.name for s in expr.free_symbols}
    if not used or not used <= set(columns):
        return None
    matches = classify(expr, {n: columns[n] for n in used}, units, top=1)
    if not matches or matches[0].r2 < min_r2:
        return None
    m = matches[0]
    entry = next(e for e in load_catalogue() if e.id == m.id)
    mapping = {sp.Symbol(ph): sp.Symbol(var) for ph, var in m.variables.items()}
    for s in entry.template.free_symbols:
        if s.name in m.variables:
            mapping[s] = sp.Symbol(m.variables[s.name])
    constants = {"c": m.coefficient, **({"k": m.k} if entry.k and m.k is not None else {})}
    clean = entry.template.xreplace({**mapping, **{s: sp.Float(constants[s.name]) for s in entry.template.free_symbols
                                                   if s.name in constants}})
    return clean, m.name, m.r2


def measured_quantities(problem: Any, traj: Any, kept: list[str], have: set[str]) -> dict[str, np.ndarray]:
    """The recorded quantities that measure a kept state through a factor of the parameters (a
    concentration ``A/V`` of an amount ``A``: :mod:`physmend.ude.measured`), as formula inputs
    ``(N,)`` along the training samples: a missing term often acts on the measured quantity, not
    on the state it is stored in (an elimination on the concentration). Only outputs that are model
    variables (a formula names them); those already in ``have`` are left out."""
    from physmend.ude.measured import recorded_quantities

    wanted = [n for n in recorded_quantities(problem.model, problem.compiled.observed_names, kept) if n not in have]
    if not wanted:
        return {}
    with torch.no_grad():
        values = problem.compiled.observed(traj.u, traj.x, traj.p)
    order = problem.compiled.observed_names
    return {n: values[:, order.index(n)].numpy() for n in wanted}


def targets(hybrid: Any, problem: Any, traj: Any, kept: list[str]) -> dict[str, np.ndarray]:
    """``a·correction`` per kept state along the training samples: ``(N,)`` each, equation units."""
    from physmend.ude.analysis import equation_corrections

    values = equation_corrections(hybrid, problem, traj, kept)
    return {name: values[:, i].numpy() for i, name in enumerate(kept)}


def estimate_shifts(hybrid: Any, problem: Any, handed: list[str]) -> list[str]:
    """``name declared → estimated (share of its range)`` for each jointly estimated parameter; one
    taken to have absorbed missing physics (``handed``, :func:`physmend.ude.analysis.absorbed`) is
    flagged: its change is in the formula's target."""
    from physmend.ude.analysis import ABSORBED_SHARE

    declared = {v.name: v for v in problem.model.parameters}
    out = []
    for name, value in hybrid.estimates().items():
        var = declared[name]
        lo, hi = var.bounds or (value, value)
        share = (value - float(var.value)) / (hi - lo) if hi > lo else 0.0
        if name not in handed:
            flag = " — calibration, left out of the formula"
        elif abs(share) > ABSORBED_SHARE:
            flag = (f" — taken to have absorbed part of the missing physics (it moved over {ABSORBED_SHARE:.0%} of "
                    "its range): handed back to the formula")
        else:
            flag = (" — taken to have absorbed part of the missing physics (its move, small against its range, changed "
                    f"a corrected equation by at least {ABSORBED_SHARE:.0%} of the network's correction there): "
                    "handed back to the formula")
        moved = f"{share:+.2%}" if abs(share) < 0.01 else f"{share:+.0%}"
        out.append(f"{name} {float(var.value):.4g} → {value:.4g} ({moved} of its range){flag}")
    return out


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
            return [_correction(problem, s, fronts[s], *picks[s], columns, units, sc, {})
                    for s in kept if s not in out and (s != state or i == 1)]

        i, why = choose_by_simulation(work, problem, state, pair, build, min(int(sc.refit_epochs), SELECTION_REFIT_STEPS))
        if i == 0:
            out[state] = why
            print(f"{state}: no correction — with the formulas of {', '.join(simulated)} in the model, its chosen "
                  f"formula ({chosen.text}) does not pay for its constants in the simulated training records.")
    return out


def _correction(problem: Any, state: str, front: Any, idx: int, why: str, columns: dict[str, np.ndarray],
                units: dict[str, str], sc: Any, chosen: dict[str, Any]) -> Any:
    """The correction for Pareto candidate ``idx`` (clean catalogue form when it fits); records ``chosen``."""
    from physmend.modeling import Correction

    unit = equation_unit(problem.model, state, getattr(problem, "time_unit", "s"))
    raw = front.candidates[idx].expr
    canonical = canonical_form(raw, columns, units, float(sc.canonical_r2))
    if canonical is not None:
        why += (f" Its form matches the catalogue's {canonical[1]!r} with R² {canonical[2]:.4f} ≥ "
                f"{float(sc.canonical_r2)} on the training samples, so that clean form is used.")
    expr, consts = name_constants(canonical[0] if canonical is not None else identifiable(raw))
    chosen[state] = {"index": idx, "why": why, "expr": str(raw), "unit": unit,
                     "canonical": str(canonical[0]) if canonical is not None else None}
    return Correction(state=state, term=sp.sstr(expr), constants=consts, unit=unit)


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


#: candidates listed per equation (besides the chosen one) unless ``symbolic.verbose``
LISTED = 5


def listed(front: Any, chosen: int, verbose: bool) -> set[int]:
    """Indices of the front's candidates to print: all when ``verbose``; otherwise the chosen one
    and the :data:`LISTED` that fit the target best (highest R²)."""
    if verbose:
        return set(range(len(front.candidates)))
    best = sorted(range(len(front.candidates)), key=lambda i: -front.candidates[i].r2)[:LISTED]
    return {chosen, *best}


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run symbolic regression on a sensitivity run (default: the latest); returns the new run ID."""
    from physmend.modeling.corrections import constant_parameter_name
    from physmend.stages.common import load_source, merged, resolve
    from physmend.symbolic import choose, fit
    from physmend.tracking import TrackingError, get_run, open_store, stage_run
    from physmend.ude.analysis import training_trajectories
    from physmend.ude.timescale import resolve_times
    from physmend.ude.metrics import checkpoint_problem
    from physmend.symbolic.choice import MIN_RECORDED_WINDOWS, independent_windows
    from physmend.symbolic import ParetoFront
    from physmend.symbolic.library import pair_candidates
    from physmend.symbolic.scaled import scaled_variants
    from physmend.ude.spec import informative_parameters, scale_parameters

    store = open_store(cfg.tracking)
    sens_run = resolve(store, source_run_id, stages=("sensitivity",), latest=source_run_id is None)
    model_run = get_run(store, sens_run.data.tags["physmend.source_run_id"])
    src = load_source(store, model_run, cfg)
    hybrid, problem = src.hybrid, src.problem
    work = resolve_times(merged(src.cfg, cfg, "symbolic"), problem)
    sc = cfg.symbolic
    kept = sens_run.data.tags.get("physmend.kept", "").split(",")
    inputs = [n for n in sens_run.data.tags.get("physmend.inputs", "").split(",") if n]
    params = informative_parameters(problem) if sc.parameters == "auto" else [str(p) for p in (sc.parameters or [])]
    unknown = [p for p in params if p not in problem.model.parameter_names]
    if unknown:
        raise TrackingError(f"symbolic.parameters names {unknown}, which are not parameters of model {problem.model.name!r}")
    # parameters seen at two values only: a scale of a form, never a free variable (physmend.symbolic.scaled)
    scale = [p for p in scale_parameters(problem) if p not in params] if sc.parameters == "auto" else []
    traj = training_trajectories(hybrid, problem, work)
    names = hybrid.spec.input_names
    with torch.no_grad():
        feats = hybrid.features(traj.u, traj.x, traj.p).numpy()
    columns = {n: feats[:, names.index(n)] for n in inputs if n in names}
    for p in params:
        columns[p] = traj.p[:, problem.model.parameter_names.index(p)].numpy()
    columns.update(measured_quantities(problem, traj, kept, set(columns)))
    x_names = list(columns)
    X = np.stack([columns[n] for n in x_names], axis=1)
    for p in scale:  # after X: not a variable of the regression
        columns[p] = traj.p[:, problem.model.parameter_names.index(p)].numpy()
    units = {n: problem.model.units.get(n, "") for n in [*x_names, *scale]}
    y_all = targets(hybrid, problem, traj, kept)
    fronts, chosen, picks = {}, {}, {}
    choices = dict(sc.choice or {})
    stray = sorted(set(choices) - set(kept))
    if stray:
        raise TrackingError(f"symbolic.choice names {stray}, but the formulas are for the kept corrections {list(kept)} "
                            "(choose a Pareto index for one of those)")
    select = str(sc.get("select", "recorded"))
    if select not in ("recorded", "rule"):
        raise TrackingError(f"symbolic.select must be 'recorded' or 'rule', but got {select!r}")
    rates = None
    window = float(work.symbolic.window)  # 'auto' resolved from the sampling interval (physmend.ude.timescale)
    if select == "recorded":
        from physmend.ude.rates import recorded_rates

        rates = recorded_rates(hybrid, problem, work, kept, float(window), traj.handed)
    # a kept equation whose state is not measured has no recorded mismatch: the simulated model decides
    simulated = [s for s in kept if select == "recorded" and choices.get(s) is None
                 and (rates is None or s not in rates.targets)]
    recorded_scores: dict[str, list[tuple[float, float]]] = {}
    operators = OmegaConf.to_container(cfg.operators) if "operators" in cfg else None  # checked when composed
    if operators is not None:  # sin/cos only where some input is an angle (physmend.symbolic.operators)
        from physmend.symbolic.operators import operators_for

        operators = operators_for(operators, {n: units[n] for n in x_names})
    for state in kept:
        front = fit(X, y_all[state], x_names, backend=str(sc.backend), target=state, units=units,
                    options=dict(sc.options or {}), seed=int(cfg.get("seed", 0)), operators=operators,
                    target_unit=equation_unit(problem.model, state, getattr(problem, "time_unit", "s")),
                    check_units=bool(sc.get("units", True)))
        if front.info.get("unit_rejected"):
            print(f"{state}: {front.info['unit_rejected']} formula(s) left out, their units cannot be the equation's "
                  f"(e.g. {front.info['unit_rejected_examples'][0]})")
        if front.info.get("interval_rejected"):
            print(f"{state}: {front.info['interval_rejected']} formula(s) left out, they use a quantity on a scale with "
                  f"an offset (°C, °F) other than as a difference (e.g. {front.info['interval_rejected_examples'][0]})")
        extra = scaled_variants(front.candidates, scale, columns, y_all[state], operators=operators, units=units)
        if select == "recorded":
            extra += catalogue_candidates([*x_names, *scale], units, columns, y_all[state], operators=operators,
                                          scale_only=set(scale))
        if extra:
            front.candidates = sorted(front.candidates + extra, key=lambda c: (c.complexity, c.mse))
        fronts[state] = front
        if rates is not None and state in rates.targets and choices.get(state) is None:
            i, why, recorded_scores[state] = choose_by_recordings(rates, state, front)
            picks[state] = (i, why)
        else:
            picks[state] = choose(front, rule=str(sc.rule), index=choices.get(state))
    for state in simulated:  # each is judged in the corrected model with the other unmeasured ones' formulas; the
        # measured equations' corrections come after (drop_needless): a network may have split one term between them
        def build(i: int, state: str = state) -> list:
            return [_correction(problem, s, fronts[s], *((i, "") if s == state else picks[s]), columns, units, sc, {})
                    for s in simulated]
        picks[state] = choose_by_simulation(work, problem, state, fronts[state], build,
                                            min(int(sc.refit_epochs), SELECTION_REFIT_STEPS))
    windows = independent_windows(rates) if rates is not None else math.inf
    short = [s for s in kept if s in recorded_scores and windows < MIN_RECORDED_WINDOWS]
    for state in short:  # a short record: the recorded mismatch is a handful of window means; every sample decides
        front = fronts[state]
        names_lib = [n for n in x_names if n not in problem.model.parameter_names]
        lib = pair_candidates(names_lib, columns, y_all[state], operators=operators, units=units)
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
            return [_correction(problem, s, fronts[s], *((shortlist[i], "") if s == state else picks[s]), columns,
                                units, sc, {}) for s in kept]
        i, why = choose_by_simulation(
            work, problem, state, sub, build_all, min(int(sc.refit_epochs), SELECTION_REFIT_STEPS),
            reason=(f"the training records give only {windows:.0f} independent windows of recorded mismatch, fewer "
                    f"than {MIN_RECORDED_WINDOWS}: the formulas they rank best and the library's products and ratios, "
                    f"{len(shortlist)} in all, are put into the model, whose simulation of every training sample "
                    "decides"))
        if why.startswith("Rule 'simulated': no formula"):  # none could be solved: the recorded choice stands
            continue
        picks[state] = (shortlist[i], why.replace(f"chose index {i} (", f"chose index {shortlist[i]} ("))
    dropped = drop_needless(work, problem, kept, simulated, choices, fronts, picks, columns, units, sc)
    kept = [s for s in kept if s not in dropped]
    fronts = {s: f for s, f in fronts.items() if s not in dropped}
    fallback = ""
    while True:
        corrections = [_correction(problem, state, fronts[state], *picks[state], columns, units, sc, chosen) for state in kept]
        # every choice below sees training and validation data only
        corrected = checkpoint_problem(corrected_problem(work, corrections))
        ref, trouble = simulate_corrected(corrected, work)
        if trouble is None:
            break
        movable = [s for s in kept if picks[s][0] > 0 and s not in choices]
        if not movable:
            raise TrackingError(f"the corrected model cannot be simulated with any formula on the fronts: {trouble}")
        worst = max(movable, key=lambda s: fronts[s].candidates[picks[s][0]].complexity)
        i = picks[worst][0] - 1
        fallback += f" Formula {picks[worst][0]} for {worst} made the corrected model fail ({trouble}); fell back to {i}."
        picks[worst] = (i, f"Fallback along the front to index {i} (a more complex formula made the corrected model unstable).")
    metrics = before = corrected_metrics(corrected, ref)
    uncertainty: dict[str, dict[str, Any]] = {}  # re-fitted constant -> value, standard error, pinned down?
    recalibrated: dict[str, float] = {}  # declared-uncertain parameter -> value re-fitted with the formulas
    iterations = int(sc.refit_epochs)
    refit_note = "constants as found by the regression (symbolic.refit_epochs=0)"
    recal = recalibratable(corrected, corrections, work) if bool(sc.get("recalibrate", True)) else []
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
                          f"{before['val.rmse']:.4g} → {after['val.rmse']:.4g})" + _uncertainty_note(result))
            uncertainty = {k: {"value": result.constants[k], "stderr": result.stderr.get(k, math.inf),
                               "pinned": result.pinned(k)} for k in result.constants}
            break
        if ref_after is None:
            refit_note = (f"the {what} re-fitted through the simulator ({how}) made the corrected model fail "
                          f"({trouble}); the regression's constants are kept")
        else:
            refit_note = (f"re-fitting the {what} through the simulator ({how}) did not improve the validation RMSE "
                          f"({before['val.rmse']:.4g} → {after['val.rmse']:.4g}); the regression's constants are kept")
    # the held-out (test) fit is the proposal's report: simulating the test records here too would
    # cost a whole-trajectory solve of each (a long record: minutes) for a figure nothing chooses by
    with stage_run(store, work, stage=STAGE, source_run_id=sens_run.info.run_id, run_name="symbolic",
                   tags={"physmend.kept": ",".join(kept), "physmend.model_run_id": model_run.info.run_id}) as run_:
        run_.log_params({"backend": sc.backend, "rule": sc.rule, "inputs": ",".join(x_names)})
        run_.log_json({s: f.to_dict() for s, f in fronts.items()}, "pareto.json")
        run_.log_json(chosen, "chosen.json")
        if uncertainty:
            run_.log_json(uncertainty, "uncertainty.json")
        from physmend.modeling.corrections import FORMAT

        import yaml

        run_.log_text(yaml.safe_dump({"physmend_corrections": FORMAT, "model": problem.model.name,
                                      "source_run_id": sens_run.info.run_id,
                                      "corrections": [c.to_dict() for c in corrections],
                                      **({"parameters": recalibrated} if recalibrated else {})}, sort_keys=False),
                      "corrections.yaml")
        run_.log_metrics({k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")})
        run_.describe("Formulas: " + "; ".join(
            f"{c.state}: + {c.term} ({', '.join(f'{k} = {v:.4g}' for k, v in c.constants.items())})" for c in corrections)
            + f". Corrected model, validation RMSE {metrics.get('val.rmse', float('nan')):.4g}. Source sensitivity run: "
            f"{sens_run.info.run_id}. Next: physmend propose <this run>.")
        run_id = run_.run_id
    lines = [f"# physmend symbolic — {sc.backend}, inputs {', '.join(x_names)}", ""]
    if fallback:
        lines += [fallback.strip(), ""]
    for state, front in fronts.items():
        lines.append(f"## {state} (correction in {chosen[state]['unit'] or 'equation units'})")
        rec = recorded_scores.get(state)
        shown = listed(front, chosen[state]["index"], bool(sc.get("verbose", False)))
        for i, c in enumerate(front.candidates):
            if i not in shown:
                continue
            mark = "→" if i == chosen[state]["index"] else " "
            extra = f"  recorded R² {rec[i][1]:.4f}" if rec else ""
            lines.append(f" {mark} [{i}] complexity {c.complexity:3d}  R² {c.r2:.4f}{extra}  {c.text}")
        if len(shown) < len(front.candidates):
            lines.append(f"   ({len(front.candidates) - len(shown)} more on the front: pareto.json of this run, or "
                         "symbolic.verbose=true)")
        lines.append(f"   chosen: {chosen[state]['why']}")
    lines.append("")
    for c in corrections:
        consts = ", ".join(f"{k} = {v:.4g}" for k, v in c.constants.items())
        lines.append(f"{c.state}: + {c.term}   ({consts})")
    lines.append(refit_note + ".")
    if recalibrated:
        declared = {v.name: float(v.value) for v in problem.model.parameters}
        lines.append("Re-calibrated with the formulas (declared uncertain; the proposal carries these values): "
                     + ", ".join(f"{n} {declared[n]:.4g} → {v:.4g}" for n, v in recalibrated.items()) + ".")
    moved = estimate_shifts(hybrid, problem, traj.handed)
    if moved:
        keeps = "re-calibrated with the formulas as above" if recalibrated else "the proposed model keeps the declared values"
        lines.append(f"Jointly estimated with the network ({keeps}): " + "; ".join(moved) + ".")
    if metrics:
        lines.append(f"Corrected model (no network): validation RMSE {metrics.get('val.rmse', float('nan')):.4g}.")
    print("\n".join(lines))
    print(f"\nsymbolic run: {run_id}\nnext: physmend propose {run_id}")
    return run_id


def _uncertainty_note(result: Any) -> str:
    """``; c1 = -0.15 ± 0.0002 (±0.1 %)`` for each re-fitted constant, and which the data cannot pin down."""
    parts = []
    for name, value in result.constants.items():
        se = result.stderr.get(name, math.inf)
        short = name  # the model parameter holding it (owner.state_cK): unique, unlike the bare cK
        if not math.isfinite(se):
            parts.append(f"{short} = {value:.4g} (the data cannot pin it down)")
        else:
            rel = f" (±{100 * se / abs(value):.2g} %)" if value else ""
            parts.append(f"{short} = {value:.4g} ± {se:.2g}{rel}" + ("" if result.pinned(name) else ", not pinned down by the data"))
    return ("; " + "; ".join(parts)) if parts else ""
