"""``physmend symbolic [RUN_ID]``: the network's corrections become formulas.

Finds the sensitivity run (default: the latest) and the trial or mask run it analysed, checks the
``symbolic`` settings against them, and hands the trained network to
:func:`physmend.symbolic.formulas.find_formulas` (targets in each equation's units, Pareto fronts,
the choice by recordings or by simulation, constants re-fitted through the simulator); then logs
the fronts, the choice and the corrections file, and prints the findings
(:func:`physmend.symbolic.summary.report`).
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf

STAGE = "symbolic"


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run symbolic regression on a sensitivity run (default: the latest); returns the new run ID."""
    import yaml

    from physmend.modeling.corrections import FORMAT
    from physmend.settings import group_settings
    from physmend.stages.common import load_source, merged, resolve
    from physmend.symbolic.formulas import find_formulas
    from physmend.symbolic.summary import report
    from physmend.tracking import TrackingError, get_run, open_store, stage_run
    from physmend.ude.analysis import training_trajectories
    from physmend.ude.spec import informative_parameters, scale_parameters
    from physmend.ude.timescale import resolve_times

    store = open_store(cfg.tracking)
    sens_run = resolve(store, source_run_id, stages=("sensitivity",), latest=source_run_id is None)
    model_run = get_run(store, sens_run.data.tags["physmend.source_run_id"])
    src = load_source(store, model_run, cfg)
    hybrid, problem = src.hybrid, src.problem
    work = resolve_times(merged(src.cfg, cfg, "symbolic"), problem)
    sc = group_settings(cfg, "symbolic")
    kept = sens_run.data.tags.get("physmend.kept", "").split(",")
    inputs = [n for n in sens_run.data.tags.get("physmend.inputs", "").split(",") if n]
    params = informative_parameters(problem) if sc.parameters == "auto" else [str(p) for p in (sc.parameters or [])]
    unknown = [p for p in params if p not in problem.model.parameter_names]
    if unknown:
        raise TrackingError(f"symbolic.parameters names {unknown}, which are not parameters of model {problem.model.name!r}")
    # parameters seen at two values only: a scale of a form, never a free variable (physmend.symbolic.scaled)
    scale = [p for p in scale_parameters(problem) if p not in params] if sc.parameters == "auto" else []
    choices = dict(sc.choice or {})
    stray = sorted(set(choices) - set(kept))
    if stray:
        raise TrackingError(f"symbolic.choice names {stray}, but the formulas are for the kept corrections {list(kept)} "
                            "(choose a Pareto index for one of those)")
    select = sc.select  # 'recorded' or 'rule', checked
    operators = OmegaConf.to_container(cfg.operators) if "operators" in cfg else None  # checked when composed
    found = find_formulas(hybrid, problem, work, sc, training_trajectories(hybrid, problem, work), kept=kept,
                          inputs=inputs, parameters=params, scale=scale, choices=choices, select=select,
                          operators=operators, seed=group_settings(cfg, "").seed)  # type: ignore[arg-type]
    corrections, metrics = found.corrections, found.metrics
    # the held-out (test) fit is the proposal's report: simulating the test records here too would
    # cost a whole-trajectory solve of each (a long record: minutes) for a figure nothing chooses by
    with stage_run(store, work, stage=STAGE, source_run_id=sens_run.info.run_id, run_name="symbolic",
                   tags={"physmend.kept": ",".join(found.kept), "physmend.model_run_id": model_run.info.run_id}) as run_:
        run_.log_params({"backend": sc.backend, "rule": sc.rule, "inputs": ",".join(found.x_names)})
        run_.log_json({s: f.to_dict() for s, f in found.fronts.items()}, "pareto.json")
        run_.log_json(found.chosen, "chosen.json")
        if found.uncertainty:
            run_.log_json(found.uncertainty, "uncertainty.json")
        run_.log_text(yaml.safe_dump({"physmend_corrections": FORMAT, "model": problem.model.name,
                                      "source_run_id": sens_run.info.run_id,
                                      "corrections": [c.to_dict() for c in corrections],
                                      **({"parameters": found.recalibrated} if found.recalibrated else {})},
                                     sort_keys=False),
                      "corrections.yaml")
        run_.log_metrics({k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse")})
        run_.describe("Formulas: " + "; ".join(
            f"{c.state}: + {c.term} ({', '.join(f'{k} = {v:.4g}' for k, v in c.constants.items())})" for c in corrections)
            + f". Corrected model, validation RMSE {metrics.get('val.rmse', float('nan')):.4g}. Source sensitivity run: "
            f"{sens_run.info.run_id}. Next: physmend propose <this run>.")
        run_id = run_.run_id
    print(report(found, sc.backend, sc.verbose))
    print(f"\nsymbolic run: {run_id}\nnext: physmend propose {run_id}")
    return run_id
