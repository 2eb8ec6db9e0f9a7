"""Times as a reader wants them: seconds in the unit that suits the record, any other declared
time unit (``data.time_unit``: ``tu``, ``dimensionless`` …) shown as it is, never converted."""

from __future__ import annotations

import numpy as np

SECONDS = "s"
_STEPS = ((3 * 86400, 86400.0, "d"), (3 * 3600, 3600.0, "h"), (180, 60.0, "min"))


def _scale(span: float, unit: str) -> tuple[float, str]:
    """``(divisor, label)`` for times of a record ``span`` long, in ``unit``."""
    if unit != SECONDS:
        return 1.0, unit
    for least, divisor, label in _STEPS:
        if span >= least:
            return divisor, label
    return 1.0, SECONDS


def clock(t: float, span: float, unit: str = SECONDS) -> str:
    """``t`` written in the unit that suits a record ``span`` long (both in ``unit``): ``2.5 h``."""
    divisor, label = _scale(span, unit)
    return f"{t / divisor:.{2 if label == 'd' else 1}f} {label}"


def axis(t: np.ndarray, unit: str = SECONDS) -> tuple[np.ndarray, float, str]:
    """``(values, divisor, label)`` to plot times ``t (T,)`` (in ``unit``) on: ``t / divisor``
    against an axis titled ``time [label]``."""
    t = np.asarray(t, dtype=float)
    finite = t[np.isfinite(t)]
    span = float(finite.max() - finite.min()) if finite.size else 0.0
    divisor, label = _scale(span, unit)
    return t / divisor, divisor, label
