"""``physmend diagnose``: simulate the model as written against every experiment; where does it miss?

Reports per experiment and output the RMSE and bias against an estimate of the sensor noise, the
time windows with the largest residuals, and the model variables and inputs that the residual
(and its drift rate) correlate with. Correlations use training/validation experiments only; test
experiments are simulated to report their error.

A model as written that diverges — an output leaves the range of the records by more than
:data:`physmend.simulate.divergence.RANGE_MARGIN` ranges, or the model blows up in finite time —
is a finding, not a failure: which state, from when (the data's time unit), against which range.
A model that blows up is simulated held inside the box of its measured states
(:func:`physmend.simulate.divergence.projected`), so there is a table all the same.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from physmend.explain import residuals as res
from physmend.explain.clock import axis, clock
from physmend.problem import Problem, load_problem
from physmend.simulate import Batch, SimulationError, Trajectories, make_batch, simulate_batch
from physmend.simulate.divergence import RANGE_MARGIN, Divergence

STAGE = "diagnose"


def analyse(problem: Problem, traj: Trajectories, t: np.ndarray, cfg: Any) -> dict[str, Any]:
    """Residual statistics, worst windows and correlates as plain data (JSON-ready)."""
    model = problem.model
    outs = model.output_names
    sim = traj.outputs.detach().cpu().numpy()
    per: list[dict[str, Any]] = []
    fitted_roles = {"train", "validation"}
    aliases = _redundant_observed(model)
    for b, exp in enumerate(problem.experiments):
        rows = np.searchsorted(t, exp.obs_time)
        span = float(exp.obs_time[-1] - exp.obs_time[0]) if exp.obs_time.size > 1 else 0.0
        for j, out in enumerate(outs):
            y = exp.obs[:, j]
            s = sim[rows, b, j]
            stats = res.error_stats(exp.obs_time, y, s)
            r = s - y
            windows = res.worst_windows(
                exp.obs_time, r, length=max(span * float(cfg.diagnose.window_fraction), 2 * _interval(exp.obs_time)),
                count=int(cfg.diagnose.n_windows),
            )
            per.append(
                {
                    "experiment": exp.id,
                    "role": exp.role,
                    "output": out,
                    "unit": model.units.get(out, ""),
                    "span": span,
                    **stats.as_dict(),
                    "windows": [asdict(w) for w in windows],
                }
            )
    # correlates over training/validation experiments, pooled
    fit_idx = [b for b, e in enumerate(problem.experiments) if e.role in fitted_roles]
    states = traj.states.detach().cpu().numpy()
    observed = traj.observed.detach().cpu().numpy()
    inputs = traj.inputs.detach().cpu().numpy()
    corr: dict[str, Any] = {}
    for j, out in enumerate(outs):
        sig_r, sig_rate = [], []
        cands: dict[str, tuple[str, list[np.ndarray]]] = {}
        for b in fit_idx:
            exp = problem.experiments[b]
            rows = np.searchsorted(t, exp.obs_time)
            r = sim[rows, b, j] - exp.obs[:, j]
            sig_r.append(r)
            sig_rate.append(res.residual_rate(exp.obs_time, r, int(cfg.diagnose.smooth_samples)))
            for i, name in enumerate(model.state_names):
                cands.setdefault(name, ("state", []))[1].append(states[rows, b, i])
            for i, name in enumerate(model.observed):
                if name not in aliases:
                    cands.setdefault(name, ("algebraic", []))[1].append(observed[rows, b, i])
            for i, name in enumerate(model.input_names):
                cands.setdefault(name, ("input", []))[1].append(inputs[rows, b, i])
        pooled = {k: (kind, np.concatenate(v)) for k, (kind, v) in cands.items()}
        n = int(cfg.diagnose.n_correlates)
        corr[out] = {
            "residual": [asdict(c) for c in res.correlates(np.concatenate(sig_r), pooled, n)] if sig_r else [],
            "drift_rate": [asdict(c) for c in res.correlates(np.concatenate(sig_rate), pooled, n)] if sig_rate else [],
        }
    return {"fits": per, "correlates": corr, "fit_experiments": [problem.experiments[b].id for b in fit_idx]}


def _redundant_observed(model: Any) -> set[str]:
    """Observed variables that repeat a state, an input, a constant or (±) another observed variable."""
    seen: set[Any] = {v.symbol for v in model.states} | {v.symbol for v in model.inputs}
    out: set[str] = set()
    for name, expr in model.observed.items():
        key = -expr if expr.could_extract_minus_sign() else expr
        if key in seen or not (expr.free_symbols - {v.symbol for v in model.parameters}):
            out.add(name)
        else:
            seen.add(key)
    return out


def _interval(t: np.ndarray) -> float:
    """Median sampling interval of the times ``t (n,)`` (0 for fewer than two)."""
    gaps = np.diff(np.asarray(t, dtype=float))
    return float(np.median(gaps)) if gaps.size else 0.0


def _ratio(x: float) -> str:
    """A ratio to the noise: one decimal, or three significant digits from 1e5 (a diverging model's 3.5e+26)."""
    return f"{x:.1f}" if not abs(x) >= 1e5 else f"{x:.3g}"


def _fmt(x: float, unit: str = "") -> str:
    return f"{x:.3g}{(' ' + unit) if unit else ''}"


def summarise(problem: Problem, analysis: dict[str, Any], cfg: Any) -> str:
    """The Markdown summary printed at the end and logged as ``summary.md``."""
    roles: dict[str, list[str]] = {}
    for e in problem.experiments:
        roles.setdefault(e.role, []).append(e.id)
    lines = [
        f"# physmend diagnose — model `{problem.model.name}`, data `{cfg.data.name}`",
        "",
        f"{problem.model.summary()}.",
        f"Simulated as written ({cfg.simulate.method}, rtol {cfg.simulate.rtol}) against "
        + ", ".join(f"{role}: {', '.join(ids)}" for role, ids in roles.items())
        + ".",
        "",
        "## Fit per experiment and output",
        "",
        "| experiment | role | output | RMSE | bias (sim − meas) | max abs | noise (est.) | RMSE / noise |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in analysis["fits"]:
        u = f["unit"]
        lines.append(
            f"| {f['experiment']} | {f['role']} | {f['output']} | {_fmt(f['rmse'], u)} | {_fmt(f['bias'], u)} | "
            f"{_fmt(f['max_abs'], u)} | {_fmt(f['noise'], u)} | {_ratio(f['ratio_to_noise'])} |"
        )
    worst = max(analysis["fits"], key=lambda f: f["ratio_to_noise"] if np.isfinite(f["ratio_to_noise"]) else -1)
    lines += ["", "## Verdict", ""]
    diverged = analysis.get("divergence") or []
    if diverged:
        lines += divergence_lines(problem, diverged)
    if worst["ratio_to_noise"] > 3:
        lines.append(
            f"The model misses the recordings: the error reaches {_ratio(worst['ratio_to_noise'])}× the estimated "
            f"sensor noise ({worst['output']}, experiment {worst['experiment']}). Something is missing or mis-sized."
        )
    else:
        lines.append(
            f"The model fits within {worst['ratio_to_noise']:.1f}× the estimated sensor noise everywhere: "
            "there is little for physmend to find."
        )
    lines += ["", "## Where the residual is largest", ""]
    for f in analysis["fits"]:
        spans = ", ".join(
            f"{clock(w['start'], f['span'], problem.time_unit)} – {clock(w['end'], f['span'], problem.time_unit)} (RMS {_fmt(w['rms'], f['unit'])}, bias {_fmt(w['bias'], f['unit'])})"
            for w in f["windows"]
        )
        lines.append(f"- experiment {f['experiment']}, {f['output']}: {spans}")
    lines += [
        "",
        "## What the mismatch correlates with",
        "",
        f"Pooled over experiments {', '.join(analysis['fit_experiments'])} (training/validation only). "
        "The drift rate (time derivative of the smoothed residual) follows the missing term more "
        "closely than the residual itself.",
        "",
    ]
    for out, c in analysis["correlates"].items():
        rate = ", ".join(f"{x['name']} ({x['kind']}, r = {x['r']:+.2f})" for x in c["drift_rate"])
        resid = ", ".join(f"{x['name']} (r = {x['r']:+.2f})" for x in c["residual"])
        lines.append(f"- **{out}** — drift rate: {rate or 'n/a'}; residual: {resid or 'n/a'}")
    return "\n".join(lines) + "\n"


def divergence_lines(problem: Problem, diverged: list[dict[str, Any]]) -> list[str]:
    """The verdict's paragraph on a model as written that diverges (``diverged``: the
    :class:`~physmend.simulate.divergence.Divergence` findings as dicts, earliest first)."""
    first = diverged[0]
    unit = problem.model.units.get(first["name"], problem.model.units.get(first["output"], ""))
    out = [f"**The model as written diverges.** First: {_finding(first, problem.time_unit, unit)}.", ""]
    for d in diverged[1:]:
        u = problem.model.units.get(d["name"], problem.model.units.get(d["output"], ""))
        out.append(f"- {_finding(d, problem.time_unit, u)}")
    if len(diverged) > 1:
        out.append("")
    if any(d["blows_up"] for d in diverged):
        out += ["From that time on the table compares the records with the model held at the edge of that range "
                f"(the recorded range widened by {RANGE_MARGIN:g} ranges): as written it has no value there.", ""]
    out += ["Something that holds the state within its range is missing (a sink, a saturation, a crowding term). "
            "Training keeps the model within the data (multiple shooting from the records): physmend sweep / "
            "discover go on.", ""]
    return out


def _finding(d: dict[str, Any], time_unit: str, unit: str) -> str:
    return Divergence(**{**d, "peak": math.inf if d["peak"] is None else d["peak"]}).describe(time_unit, unit)


def simulate_as_written(problem: Problem, batch: Batch, cfg: Any) -> tuple[Trajectories, list[Divergence]]:
    """The model as written on every experiment, and where it diverges (nothing written).

    Where the solve fails and the model can be held inside the box of its measured states
    (a finite-time blow-up), the held solve's trajectories; the failure is raised where it cannot,
    or where the held solve reaches no box (the failure is not a divergence)."""
    from physmend.ude.reference import find_divergence, output_boxes, state_boxes

    opts = {"method": str(cfg.simulate.method), "rtol": float(cfg.simulate.rtol), "atol": float(cfg.simulate.atol),
            "options": dict(cfg.simulate.options or {})}
    with torch.no_grad():
        try:
            traj = simulate_batch(problem.compiled, batch, **opts)
            return traj, find_divergence(problem, batch, traj.outputs)
        except SimulationError as exc:
            _, _, box_lo, box_hi = output_boxes(problem, batch)
            lo, hi = state_boxes(problem, batch, box_lo, box_hi)
            if not bool((torch.isfinite(lo) | torch.isfinite(hi)).any()):
                raise
            try:
                traj = simulate_batch(problem.compiled, batch, **opts, box=(lo, hi))
            except SimulationError:
                raise exc from None
            found = find_divergence(problem, batch, traj.outputs, blows_up=True)
            if not found:
                raise exc from None
            return traj, found


def _json_ready(d: Divergence) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.as_dict().items()}


def plot_experiment(problem: Problem, t: np.ndarray, traj: Trajectories, b: int) -> Any:
    """Measured vs simulated outputs and the residual for batch element ``b``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    exp = problem.experiments[b]
    outs = problem.model.output_names
    rows = np.searchsorted(t, exp.obs_time)
    sim = traj.outputs.detach().cpu().numpy()[rows, b]
    fig, axes = plt.subplots(len(outs), 2, figsize=(12, 2.8 * len(outs)), squeeze=False)
    hours, _, time_label = axis(exp.obs_time, problem.time_unit)
    for j, out in enumerate(outs):
        unit = problem.model.units.get(out, "")
        ax = axes[j, 0]
        ax.plot(hours, exp.obs[:, j], ".", ms=2, color="0.4", label="measured")
        ax.plot(hours, sim[:, j], "-", color="C3", lw=1.2, label="model as written")
        ax.set_ylabel(f"{out} [{unit}]")
        ax.legend(loc="best", fontsize=8)
        ax2 = axes[j, 1]
        ax2.plot(hours, sim[:, j] - exp.obs[:, j], ".", ms=2, color="C0")
        ax2.axhline(0, color="k", lw=0.6)
        ax2.set_ylabel(f"residual sim − meas [{unit}]")
    for ax in axes[-1]:
        ax.set_xlabel(f"time [{time_label}]")
    fig.suptitle(f"experiment {exp.id} ({exp.role})")
    fig.tight_layout()
    return fig


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the diagnose stage; returns the MLflow run ID. Nothing is written if the inputs are bad."""
    from physmend.tracking import open_store, stage_run

    problem = load_problem(cfg)
    from physmend.stages.activity import activity

    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with activity(f"diagnose: simulating {len(problem.experiments)} experiments as written"):
        traj, diverged = simulate_as_written(problem, batch, cfg)
    t = batch.t.cpu().numpy()
    with activity("diagnose: locating the mismatch"):
        analysis = analyse(problem, traj, t, cfg)
    if diverged:
        analysis["divergence"] = [_json_ready(d) for d in diverged]
    summary = summarise(problem, analysis, cfg)

    store = open_store(cfg.tracking)
    with stage_run(store, cfg, stage=STAGE, source_run_id=source_run_id, run_name="diagnose") as run_:
        run_.log_params(
            {
                "model": problem.model.name,
                "data": cfg.data.name,
                "n_states": len(problem.model.states),
                "n_experiments": len(problem.experiments),
                "simulate.method": cfg.simulate.method,
            }
        )
        worst = max(analysis["fits"], key=lambda f: f["rmse"] / f["noise"] if f["noise"] > 0 else 0.0, default=None)
        if diverged:
            d = diverged[0]
            how = "blows up in finite time" if d.blows_up else "grows without bound"
            run_.describe(f"The model as written diverges: {d.name} {how}, leaving the recorded range at "
                          f"t = {d.time:.4g} {problem.time_unit} (experiment {d.experiment}). Next: physmend sweep.")
        elif worst is not None and worst["noise"] > 0:
            run_.describe(f"The model as written misses by up to {worst['rmse'] / worst['noise']:.1f}× the estimated sensor "
                          f"noise ({worst['output']}, experiment {worst['experiment']}). Next: physmend sweep.")
        metrics: dict[str, float] = {}
        for f in analysis["fits"]:
            key = f"{f['experiment']}.{f['output']}"
            metrics[f"rmse.{key}"] = f["rmse"]
            metrics[f"bias.{key}"] = f["bias"]
            metrics[f"noise.{key}"] = f["noise"]
        for d in diverged:
            metrics.setdefault(f"diverges_at.{d.experiment}", d.time)  # the earliest output of each experiment
        finite = [f["ratio_to_noise"] for f in analysis["fits"] if np.isfinite(f["ratio_to_noise"])]
        if finite:
            metrics["max_rmse_to_noise"] = max(finite)
        run_.log_metrics({k: v for k, v in metrics.items() if np.isfinite(v)})
        run_.log_json(analysis, "diagnosis.json")
        run_.log_text(summary, "summary.md")
        if bool(cfg.diagnose.plots):
            import matplotlib.pyplot as plt

            for b, exp in enumerate(problem.experiments):
                fig = plot_experiment(problem, t, traj, b)
                run_.log_figure(fig, f"plots/fit_{exp.id}.png")
                plt.close(fig)
        run_id = run_.run_id
    print(summary)
    print(f"diagnose run: {run_id}  (browse: physmend ui)")
    print("next: physmend sweep      # train corrections for what is missing (or: physmend discover, every stage)")
    return run_id
