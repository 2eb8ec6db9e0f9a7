"""The proposal's report in Markdown (rendered to HTML by :mod:`physmend.explain.report`): the
equations corrected, each term's size and suggested mechanism, re-calibrated parameters, the fits
before and after, divergences, and one figure per experiment."""

from __future__ import annotations

from typing import Any

import sympy as sp

MIN_MECHANISM_R2 = 0.9  # a mechanism is suggested only when its form reproduces the term this well


def markdown(title: str, source_run_id: str, written: Any, time_unit: str, terms: list[dict[str, Any]],
             recalibrated: dict[str, float], rows: list[dict[str, Any]], diverged_before: list[Any],
             diverged_after: list[Any], experiments: list[Any]) -> tuple[str, dict[str, str]]:
    """The report (Markdown) and, per code-span text, its MathML (for the HTML page).

    ``written``: the model as written; ``terms``: :func:`physmend.proposal.terms.describe_terms`
    (each one's ``sympy`` entry is taken out: the rest is JSON-ready); ``rows``:
    :func:`physmend.proposal.fits.fit_rows`; ``diverged_*``: the divergences of the model as
    written and of the corrected model."""
    from physmend.explain.report import mathml

    md = [f"# {title}", "", f"Source: symbolic run {source_run_id}. Nothing changes your model until "
          f"`physmend accept <this run>`.", "", "## Equations corrected", ""]
    math: dict[str, str] = {}  # code-span text -> MathML, for the HTML page
    for t in terms:
        consts = ", ".join(f"`{k} = {v:.4g}`" for k, v in t["constants"].items())
        eq = written.equations.get(t["state"])
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
        declared = {v.name: v for v in written.parameters}
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
    unit_of = written.units
    for label, found in (("model as written", diverged_before), ("corrected model", diverged_after)):
        for d in found:
            md.append(f"- The {label} diverges: {d.describe(time_unit, unit_of.get(d.name, ''))}.")
    if diverged_before or diverged_after:
        md.append("")
    held = [r for r in rows if r["role"] == "test"]
    if held:
        md.append(f"Held-out experiments (never used for any choice): RMSE improved "
                  f"{min(r['improvement'] for r in held):.1f}× to {max(r['improvement'] for r in held):.1f}×.")
    md += ["", "## Plots", ""] + [f"![fit {e.id}](plots/fit_{e.id}.png)" for e in experiments]
    return "\n".join(md) + "\n", math
