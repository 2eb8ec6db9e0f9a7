"""What the estimates say in words: how far each parameter estimated jointly with the network moved
(and whether it took part of the missing physics), and how well the re-fit pinned the formulas'
constants down."""

from __future__ import annotations

import math
from typing import Any


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


def uncertainty_note(result: Any) -> str:
    """``; c1 = -0.15 ± 0.0002 (±0.1 %)`` for each re-fitted constant of ``result`` (a
    :class:`~physmend.symbolic.refit.RefitResult`), and which the data cannot pin down."""
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
