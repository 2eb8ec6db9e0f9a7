"""``physmend symbolic [RUN_ID]``: the network's corrections become formulas.

For every kept equation the target is the correction in the units of that equation's terms
(``a·ΔNN`` for an equation ``a·der(x) = …``: watts for a heat balance), so a formula need not
know capacities and generalises across configurations. Inputs: the inputs passed on by the
sensitivity run plus ``symbolic.parameters``. A back end returns a Pareto front (accuracy vs
complexity); one formula per equation is chosen by a stated rule (or by index), its numeric
constants are named, and they are re-fitted by simulating the corrected model (multiple
shooting, the constants estimated as model parameters, no network).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp
import torch
from omegaconf import OmegaConf

STAGE = "symbolic"


def equation_unit(model: Any, state: str) -> str:
    """The unit of the terms of ``state``'s equation (from a variable in its right-hand side)."""
    eq = model.equations.get(state)
    if eq is None:
        return ""
    for sym in sorted(eq.rhs.free_symbols, key=lambda s: s.name):
        unit = model.units.get(sym.name, "")
        if unit and sym.name not in model.parameter_names:
            return unit
    return ""


def name_constants(expr: sp.Expr, prefix: str = "c") -> tuple[sp.Expr, dict[str, float]]:
    """Replace the floating-point constants of ``expr`` by symbols ``c1, c2 …``; returns both."""
    consts: dict[str, float] = {}
    mapping: dict[sp.Basic, sp.Symbol] = {}
    for k, f in enumerate(sorted(expr.atoms(sp.Float), key=lambda a: (-abs(float(a)), float(a))), 1):
        name = f"{prefix}{k}"
        mapping[f] = sp.Symbol(name)
        consts[name] = float(f)
    return expr.xreplace(mapping), consts


def targets(hybrid: Any, problem: Any, traj: Any, kept: list[str]) -> dict[str, np.ndarray]:
    """``a·correction`` per kept state along the training samples: ``(N,)`` each, equation units."""
    from physmend.modeling.compile import lambdify_torch

    model = problem.model
    out = {}
    psyms = [v.symbol for v in model.parameters]
    for name in kept:
        col = hybrid.spec.corrected.index(name)
        coef = lambdify_torch(psyms, [model.der_coefficient[name]], "der coefficient")(*traj.p.unbind(-1))[0]
        coef = torch.as_tensor(coef, dtype=traj.p.dtype).expand(traj.p.shape[0])
        out[name] = (coef * traj.corr[:, col]).numpy()
    return out


def refit(cfg: Any, problem_cfg: Any, corrections: list, epochs: int) -> tuple[list, dict[str, float]]:
    """Re-fit the correction constants by training the corrected model (no network) on the data."""
    from physmend.modeling import Correction, write_corrections
    from physmend.problem import load_problem
    from physmend.ude import train

    with tempfile.TemporaryDirectory(prefix="physmend-refit-") as tmp:
        path = write_corrections(Path(tmp) / "candidate.yaml", corrections)
        work = OmegaConf.create(OmegaConf.to_container(problem_cfg, resolve=True))
        work.model.corrections = str(path)
        problem = load_problem(work)
        # constants become uncertain parameters: estimated by multiple shooting, network off
        from physmend.modeling import apply_corrections, load_model

        base = load_model(str(work.model.builder), work.model.get("options") or {})
        problem.model = apply_corrections(base, corrections, estimate=True).simplify()
        from physmend.modeling import compile_model

        problem.compiled = compile_model(problem.model)
        work.ude.corrected = []
        work.train.epochs = epochs
        work.train.estimate_parameters = True
        work.train.lr = float(cfg.symbolic.refit_lr)
        result = train(work, problem)
    fitted = []
    for c in corrections:
        owner = problem.model.owner.get(c.state, "")
        from physmend.modeling.corrections import constant_parameter_name

        new = {k: result.metrics.get(f"estimate.{constant_parameter_name(owner, c.state, k)}", v) for k, v in c.constants.items()}
        fitted.append(Correction(state=c.state, term=c.term, constants=new, unit=c.unit, mechanism=c.mechanism))
    return fitted, result.metrics


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run symbolic regression on a sensitivity run (default: the latest); returns the new run ID."""
    from physmend.modeling import Correction
    from physmend.stages.common import load_source, merged, resolve
    from physmend.symbolic import choose, fit
    from physmend.tracking import TrackingError, get_run, open_store, stage_run
    from physmend.ude.analysis import training_trajectories
    from physmend.ude.train import varying_parameters

    store = open_store(cfg.tracking)
    sens_run = resolve(store, source_run_id, stages=("sensitivity",), latest=source_run_id is None)
    model_run = get_run(store, sens_run.data.tags["physmend.source_run_id"])
    src = load_source(store, model_run)
    work = merged(src.cfg, cfg, "symbolic")
    hybrid, problem = src.hybrid, src.problem
    sc = cfg.symbolic
    kept = sens_run.data.tags.get("physmend.kept", "").split(",")
    inputs = [n for n in sens_run.data.tags.get("physmend.inputs", "").split(",") if n]
    params = varying_parameters(problem) if sc.parameters == "auto" else [str(p) for p in (sc.parameters or [])]
    unknown = [p for p in params if p not in problem.model.parameter_names]
    if unknown:
        raise TrackingError(f"symbolic.parameters names {unknown}, which are not parameters of model {problem.model.name!r}")
    traj = training_trajectories(hybrid, problem, work)
    names = hybrid.spec.input_names
    with torch.no_grad():
        feats = hybrid.features(traj.u, traj.x, traj.p).numpy()
    columns = {n: feats[:, names.index(n)] for n in inputs if n in names}
    for p in params:
        columns[p] = traj.p[:, problem.model.parameter_names.index(p)].numpy()
    x_names = list(columns)
    X = np.stack([columns[n] for n in x_names], axis=1)
    units = {n: problem.model.units.get(n, "") for n in x_names}
    y_all = targets(hybrid, problem, traj, kept)
    fronts, chosen, corrections = {}, {}, []
    choices = dict(sc.choice or {})
    for state in kept:
        unit = equation_unit(problem.model, state)
        front = fit(X, y_all[state], x_names, backend=str(sc.backend), target=state, units=units,
                    options=dict(sc.options or {}), seed=int(cfg.get("seed", 0)))
        idx, why = choose(front, rule=str(sc.rule), index=choices.get(state))
        fronts[state] = front
        expr, consts = name_constants(front.candidates[idx].expr)
        chosen[state] = {"index": idx, "why": why, "expr": str(front.candidates[idx].expr), "unit": unit}
        corrections.append(Correction(state=state, term=sp.sstr(expr), constants=consts, unit=unit))
    metrics: dict[str, float] = {}
    if int(sc.refit_epochs) > 0:
        corrections, metrics = refit(cfg, work, corrections, int(sc.refit_epochs))
    with stage_run(store, work, stage=STAGE, source_run_id=sens_run.info.run_id, run_name="symbolic",
                   tags={"physmend.kept": ",".join(kept), "physmend.model_run_id": model_run.info.run_id}) as run_:
        run_.log_params({"backend": sc.backend, "rule": sc.rule, "inputs": ",".join(x_names)})
        run_.log_json({s: f.to_dict() for s, f in fronts.items()}, "pareto.json")
        run_.log_json(chosen, "chosen.json")
        from physmend.modeling.corrections import FORMAT

        import yaml

        run_.log_text(yaml.safe_dump({"physmend_corrections": FORMAT, "model": problem.model.name,
                                      "source_run_id": sens_run.info.run_id,
                                      "corrections": [c.to_dict() for c in corrections]}, sort_keys=False),
                      "corrections.yaml")
        run_.log_metrics({k: v for k, v in metrics.items() if k in ("val.rmse", "train.rmse", "test.rmse")})
        run_id = run_.run_id
    lines = [f"# physmend symbolic — {sc.backend}, inputs {', '.join(x_names)}", ""]
    for state, front in fronts.items():
        lines.append(f"## {state} (correction in {chosen[state]['unit'] or 'equation units'})")
        for i, c in enumerate(front.candidates):
            mark = "→" if i == chosen[state]["index"] else " "
            lines.append(f" {mark} [{i}] complexity {c.complexity:3d}  R² {c.r2:.4f}  {c.text}")
        lines.append(f"   chosen: {chosen[state]['why']}")
    lines.append("")
    for c in corrections:
        consts = ", ".join(f"{k} = {v:.4g}" for k, v in c.constants.items())
        lines.append(f"{c.state}: + {c.term}   ({consts}; re-fitted through the simulator)")
    if metrics:
        lines.append(f"Corrected model (no network): validation RMSE {metrics.get('val.rmse', float('nan')):.4g}.")
    print("\n".join(lines))
    print(f"\nsymbolic run: {run_id}\nnext: physmend propose {run_id}")
    return run_id
