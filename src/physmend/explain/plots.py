"""Figures shared by stages: measured outputs against simulated ones."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def fit_figure(
    t: np.ndarray,
    measured: np.ndarray,
    curves: Sequence[tuple[str, np.ndarray, dict[str, Any]]],
    outputs: Sequence[str],
    units: dict[str, str],
    title: str,
    split: float | None = None,
    time_unit: str = "s",
) -> Any:
    """One panel per output: ``measured (T, k)`` (NaN = not measured) as dots and each
    ``(label, values (T, k), plot style)`` curve against times ``t (T,)`` in ``time_unit`` (seconds
    shown in the unit that suits the record, :mod:`physmend.explain.clock`); ``split`` marks the validation split."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from physmend.explain.clock import axis

    t_axis, divisor, label = axis(t, time_unit)
    fig, axes = plt.subplots(len(outputs), 1, figsize=(10, 2.6 * len(outputs)), squeeze=False)
    for j, out in enumerate(outputs):
        ax = axes[j, 0]
        m = np.isfinite(measured[:, j])
        ax.plot(t_axis[m], measured[m, j], ".", ms=2, color="0.5", label="measured")
        for name, values, style in curves:  # (not `label`: that is the time axis's)
            ax.plot(t_axis, values[:, j], label=name, **style)
        if split is not None:
            ax.axvline(split / divisor, color="k", lw=0.6, ls=":")
        ax.set_ylabel(f"{out} [{units.get(out, '')}]")
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel(f"time [{label}]")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
