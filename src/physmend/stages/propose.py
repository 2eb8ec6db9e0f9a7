"""``physmend propose [RUN_ID]``: the corrected model, validated on held-out experiments, with a report.

Simulates the model as written and the corrected model (the user's equations plus the chosen
formulas, attached to the equations they correct) on every experiment, and writes a Markdown and
HTML report: the equations corrected, the formula, its size in physical units, before/after
fits and RMSE per experiment against the sensor noise, and the physical mechanism its form
suggests (from the mechanism catalogue). Nothing changes the user's model until ``accept``.
"""

from __future__ import annotations

import io
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import sympy as sp
import torch

STAGE = "propose"
MIN_MECHANISM_R2 = 0.9  # a mechanism is suggested only when its form reproduces the term this well


def _simulate(problem: Any, cfg: Any) -> tuple[Any, Any, list[Any]]:
    """Every experiment of ``problem`` simulated whole, and where the model diverges: a model that
    blows up (the model as written, or a corrected one on a held-out experiment) is held inside the
    box of its records from then on and reported, never a failed stage
    (:func:`physmend.diagnosis.simulate_as_written`)."""
    from physmend.simulate import make_batch
    from physmend.diagnosis import simulate_as_written

    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    traj, diverged = simulate_as_written(problem, batch, cfg)
    return batch, traj, list(diverged)


def _rmse(err: torch.Tensor) -> float:
    e = err[torch.isfinite(err)]
    return float(e.pow(2).mean().sqrt()) if e.numel() else float("nan")


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the propose stage on a symbolic run (default: the latest); returns the new run ID."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from physmend.explain.mechanisms import classify
    from physmend.explain.plots import fit_figure
    from physmend.explain.report import mathml, to_html
    from physmend.explain.residuals import noise_floor
    from physmend.modeling import read_corrections
    from physmend.modeling.expressions import parse_expression
    from physmend.problem import load_problem
    from physmend.stages.common import merged, resolve
    from physmend.tracking import download_artifact, open_store, stage_run
    from physmend.tracking.fingerprint import check_same_model
    from physmend.tracking.stored_config import read_stored_config

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("symbolic",), latest=source_run_id is None)
    cfg_path = download_artifact(store, src_run.info.run_id, "config.yaml")
    corr_path = download_artifact(store, src_run.info.run_id, "corrections.yaml")
    base_cfg = merged(read_stored_config(cfg_path, src_run.info.run_id, cfg), cfg, "propose")
    base_cfg.model.corrections = None
    corrections, meta = read_corrections(corr_path)
    recalibrated = meta["parameters"]
    before = load_problem(base_cfg)
    check_same_model(store, src_run, base_cfg)
    fixed_cfg = base_cfg.copy()
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "corrections.yaml"
        local.write_text(Path(corr_path).read_text())
        fixed_cfg.model.corrections = str(local)
        after = load_problem(fixed_cfg)
    from physmend.stages.activity import activity

    with activity(f"propose: simulating the model as written and corrected on {len(before.experiments)} experiments"):
        batch, traj0, diverged0 = _simulate(before, base_cfg)
        batch1, traj1, diverged1 = _simulate(after, base_cfg)
    outs = before.model.output_names
    rows = []
    for b, e in enumerate(before.experiments):
        for j, out in enumerate(outs):
            y = batch.obs[:, b, j]
            r0, r1 = _rmse(traj0.outputs[:, b, j] - y), _rmse(traj1.outputs[:, b, j] - y)
            m = torch.isfinite(y)
            noise = noise_floor(batch.t[m].numpy(), y[m].numpy())
            rows.append({"experiment": e.id, "role": e.role, "output": out, "before": r0, "after": r1,
                         "noise": noise, "improvement": r0 / r1 if r1 > 0 else float("inf")})
    # the formulas along the corrected trajectories (training experiments) and their mechanisms
    sm = after.model
    train_b = [b for b, e in enumerate(after.experiments) if e.role == "train"]
    samples: dict[str, np.ndarray] = {}
    names_all = sm.state_names + sm.input_names
    values_all = torch.cat([traj1.states, traj1.inputs], -1)
    for i, n in enumerate(names_all):
        samples[n] = values_all[:, train_b, i].reshape(-1).numpy()
    for i, n in enumerate(sm.observed):
        samples[n] = traj1.observed[:, train_b, i].reshape(-1).numpy()
    for i, n in enumerate(sm.parameter_names):
        samples[n] = np.repeat(batch1.params[train_b, i].numpy()[None], batch1.t.shape[0], 0).reshape(-1)
    terms = []
    symbols = {v.name: v.symbol for v in sm.states + sm.inputs + sm.parameters}
    symbols.update({n: sp.Symbol(n) for n in sm.observed if n not in symbols})  # a formula may use a recorded quantity
    for c in corrections:
        consts = {k: v for k, v in c.constants.items()}
        expr = parse_expression(c.term, {**symbols, **{k: sp.Symbol(k) for k in consts}}, where=c.state)
        expr_num = expr.subs(consts)
        from physmend.modeling.compile import lambdify_torch

        fn = lambdify_torch(list(symbols.values()), [expr_num], "correction")
        vals = fn(*[torch.as_tensor(samples[n]) for n in symbols])[0]
        vals = torch.as_tensor(vals).expand(len(next(iter(samples.values())))).numpy()
        units = {n: sm.units.get(n, "") for n in samples}
        matches = classify(expr_num, {n: samples[n] for n in samples if n in {s.name for s in expr_num.free_symbols}}, units)
        terms.append({"state": c.state, "term": c.term, "sympy": expr, "constants": consts, "unit": c.unit, "expr": str(expr_num),
                      "equation": before.model.equation_text.get(c.state, ""), "owner": sm.owner.get(c.state, ""),
                      "mean_abs": float(np.mean(np.abs(vals))), "max_abs": float(np.max(np.abs(vals))),
                      "mechanisms": [m.__dict__ for m in matches]})
    title = f"physmend proposal — model {before.model.name}"
    md = [f"# {title}", "", f"Source: symbolic run {src_run.info.run_id}. Nothing changes your model until "
          f"`physmend accept <this run>`.", "", "## Equations corrected", ""]
    math: dict[str, str] = {}  # code-span text -> MathML, for the HTML page
    for t in terms:
        consts = ", ".join(f"`{k} = {v:.4g}`" for k, v in t["constants"].items())
        eq = before.model.equations.get(t["state"])
        if eq is not None and t["equation"]:
            math[t["equation"]] = mathml(sp.Eq(eq.lhs, eq.rhs, evaluate=False))
        math[t["term"]] = mathml(t.pop("sympy"))
        md += [f"- **{t['state']}** (component `{t['owner']}`): `{t['equation']}`, plus the term `{t['term']}`"
               + (f" with {consts}" if consts else ""),
               f"- size along the training trajectories: mean |term| = {t['mean_abs']:.3g} {t['unit']}, "
               f"max |term| = {t['max_abs']:.3g} {t['unit']}"]
        good = [m for m in t["mechanisms"] if m["r2"] >= MIN_MECHANISM_R2]
        for m in good[:2]:
            md.append(f"- suggested mechanism: **{m['name']}** — {m['explanation']} (form match R² {m['r2']:.3f})")
        if not good:
            best = t["mechanisms"][0] if t["mechanisms"] else None
            md.append("- no catalogued mechanism matches this form" + (
                f" (closest: {best['name']}, R² {best['r2']:.2f})" if best else ""))
        md.append("")
    if recalibrated:
        declared = {v.name: v for v in before.model.parameters}
        md += ["## Parameters re-calibrated with the terms", "",
               "Declared uncertain in your model, re-fitted together with the terms' constants (a value calibrated "
               "without the missing term only fits without it):", ""]
        md += [f"- `{n}`: {float(declared[n].value):.4g} → {v:.4g} {'' if declared[n].unit in ('', '1') else declared[n].unit}".rstrip()
               + f" (declared bounds {declared[n].bounds[0]:g}–{declared[n].bounds[1]:g})" for n, v in recalibrated.items()]
        md.append("")
    md += ["## Fit before and after (whole-trajectory simulation)", "",
           "| experiment | role | output | RMSE before | RMSE after | improvement | noise (est.) | after / noise |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['experiment']} | {r['role']} | {r['output']} | {r['before']:.3g} | {r['after']:.3g} | "
                  f"{r['improvement']:.1f}× | {r['noise']:.3g} | {r['after'] / r['noise']:.1f} |")
    md.append("")
    unit_of = before.model.units
    for label, found in (("model as written", diverged0), ("corrected model", diverged1)):
        for d in found:
            md.append(f"- The {label} diverges: {d.describe(before.time_unit, unit_of.get(d.name, ''))}.")
    if diverged0 or diverged1:
        md.append("")
    held = [r for r in rows if r["role"] == "test"]
    if held:
        md.append(f"Held-out experiments (never used for any choice): RMSE improved "
                  f"{min(r['improvement'] for r in held):.1f}× to {max(r['improvement'] for r in held):.1f}×.")
    md += ["", "## Plots", ""] + [f"![fit {e.id}](plots/fit_{e.id}.png)" for e in before.experiments]
    report = "\n".join(md) + "\n"
    with stage_run(store, base_cfg, stage=STAGE, source_run_id=src_run.info.run_id, run_name="propose") as run_:
        run_.log_metrics({f"rmse_before.{r['experiment']}.{r['output']}": r["before"] for r in rows})
        run_.log_metrics({f"rmse_after.{r['experiment']}.{r['output']}": r["after"] for r in rows})
        run_.log_json({"rows": rows, "terms": terms, "parameters": recalibrated}, "proposal.json")
        run_.log_text(report, "report.md")
        run_.describe("Corrections: " + "; ".join(f"{t['state']} + {t['term']}" for t in terms)
                      + (f". Held-out RMSE improved {min(r['improvement'] for r in held):.1f}× to "
                         f"{max(r['improvement'] for r in held):.1f}×" if held else "")
                      + f". Report: report.html. Source symbolic run: {src_run.info.run_id}. "
                      "Next: physmend accept <this run> (or reject, or export).")
        run_.log_text(Path(corr_path).read_text(), "corrections.yaml")
        images: dict[str, bytes] = {}  # embedded in report.html, which then shows them wherever it is opened
        if bool(cfg.propose.plots):
            t = batch.t.numpy()
            for b, e in enumerate(before.experiments):
                curves = [("model as written", traj0.outputs[:, b].numpy(), {"ls": "--", "color": "C3", "lw": 1}),
                          ("corrected model", traj1.outputs[:, b].numpy(), {"color": "C2", "lw": 1.2})]
                fig = fit_figure(t, batch.obs[:, b].numpy(), curves, outs, before.model.units,
                                 f"experiment {e.id} ({e.role})", time_unit=before.time_unit)
                run_.log_figure(fig, f"plots/fit_{e.id}.png")
                png = io.BytesIO()
                fig.savefig(png, format="png")
                images[f"plots/fit_{e.id}.png"] = png.getvalue()
                plt.close(fig)
        run_.log_text(to_html(report, title, images, math), "report.html")
        run_id = run_.run_id
    print(report)
    from physmend.redact import redact

    where = redact(str(store.client.get_run(run_id).info.artifact_uri))
    print(f"propose run: {run_id}\nreport: {where}/report.html  (and report.md; in the MLflow UI: physmend ui, this run, "
          f"Artifacts)\nnext: physmend accept {run_id}   (or: physmend reject {run_id} decide.reason='…'; "
          f"physmend export {run_id} for LaTeX, sympy, Python, the network, PEtab)")
    return run_id
