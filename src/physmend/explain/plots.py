"""Figures shared by stages: measured outputs against simulated ones."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def fit_figure(
    t_hours: np.ndarray,
    measured: np.ndarray,
    curves: Sequence[tuple[str, np.ndarray, dict[str, Any]]],
    outputs: Sequence[str],
    units: dict[str, str],
    title: str,
    split_hours: float | None = None,
) -> Any:
    """One panel per output: ``measured (T, k)`` (NaN = not measured) as dots and each
    ``(label, values (T, k), plot style)`` curve; ``split_hours`` marks the validation split."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(outputs), 1, figsize=(10, 2.6 * len(outputs)), squeeze=False)
    for j, out in enumerate(outputs):
        ax = axes[j, 0]
        m = np.isfinite(measured[:, j])
        ax.plot(t_hours[m], measured[m, j], ".", ms=2, color="0.5", label="measured")
        for label, values, style in curves:
            ax.plot(t_hours, values[:, j], label=label, **style)
        if split_hours is not None:
            ax.axvline(split_hours, color="k", lw=0.6, ls=":")
        ax.set_ylabel(f"{out} [{units.get(out, '')}]")
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [h]")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
