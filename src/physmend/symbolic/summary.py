"""The symbolic stage's findings in words: the fronts (a few candidates each), the chosen formulas,
what the re-fit of their constants did, and how far jointly estimated parameters moved."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from physmend.symbolic.formulas import Formulas

#: candidates listed per equation (besides the chosen one) unless ``symbolic.verbose``
LISTED = 5


def listed(front: Any, chosen: int, verbose: bool) -> set[int]:
    """Indices of the front's candidates to print: all when ``verbose``; otherwise the chosen one
    and the :data:`LISTED` that fit the target best (highest R²)."""
    if verbose:
        return set(range(len(front.candidates)))
    best = sorted(range(len(front.candidates)), key=lambda i: -front.candidates[i].r2)[:LISTED]
    return {chosen, *best}


def report(found: Formulas, backend: str, verbose: bool) -> str:
    """The Markdown the symbolic stage prints: per kept equation the listed candidates of its
    front (``→`` the chosen one) and why it was chosen, then the formulas with their constants, the
    re-fit, re-calibrated and jointly estimated parameters and the corrected model's validation RMSE."""
    lines = [f"# physmend symbolic — {backend}, inputs {', '.join(found.x_names)}", ""]
    if found.fallback:
        lines += [found.fallback.strip(), ""]
    chosen = found.chosen
    for state, front in found.fronts.items():
        lines.append(f"## {state} (correction in {chosen[state]['unit'] or 'equation units'})")
        rec = found.recorded_scores.get(state)
        shown = listed(front, chosen[state]["index"], verbose)
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
    for c in found.corrections:
        consts = ", ".join(f"{k} = {v:.4g}" for k, v in c.constants.items())
        lines.append(f"{c.state}: + {c.term}   ({consts})")
    lines.append(found.refit_note + ".")
    if found.recalibrated:
        lines.append("Re-calibrated with the formulas (declared uncertain; the proposal carries these values): "
                     + ", ".join(f"{n} {found.declared[n]:.4g} → {v:.4g}" for n, v in found.recalibrated.items()) + ".")
    if found.shifts:
        keeps = ("re-calibrated with the formulas as above" if found.recalibrated
                 else "the proposed model keeps the declared values")
        lines.append(f"Jointly estimated with the network ({keeps}): " + "; ".join(found.shifts) + ".")
    if found.metrics:
        lines.append(f"Corrected model (no network): validation RMSE {found.metrics.get('val.rmse', float('nan')):.4g}.")
    return "\n".join(lines)
