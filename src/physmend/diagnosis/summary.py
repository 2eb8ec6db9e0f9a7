"""The diagnosis in words: the Markdown summary printed and logged as ``summary.md``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physmend.explain.clock import clock
from physmend.problem import Problem
from physmend.settings import SimulateSettings
from physmend.simulate.divergence import RANGE_MARGIN, Divergence


def _ratio(x: float) -> str:
    """A ratio to the noise: one decimal, or three significant digits from 1e5 (a diverging model's 3.5e+26)."""
    return f"{x:.1f}" if not abs(x) >= 1e5 else f"{x:.3g}"


def _fmt(x: float, unit: str = "") -> str:
    return f"{x:.3g}{(' ' + unit) if unit else ''}"


def summarise(problem: Problem, analysis: dict[str, Any], cfg: Any) -> str:
    """The Markdown summary printed at the end and logged as ``summary.md`` (``analysis``: what
    :func:`physmend.diagnosis.analysis.analyse` found, with the ``divergence`` findings if any)."""
    simulate = SimulateSettings.build(cfg.simulate)
    roles: dict[str, list[str]] = {}
    for e in problem.experiments:
        roles.setdefault(e.role, []).append(e.id)
    lines = [
        f"# physmend diagnose — model `{problem.model.name}`, data `{cfg.data.name}`",
        "",
        f"{problem.model.summary()}.",
        f"Simulated as written ({simulate.method}, rtol {simulate.rtol}) against "
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
