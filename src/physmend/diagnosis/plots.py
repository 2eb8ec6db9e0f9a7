"""The diagnosis's figure per experiment: measured against simulated outputs, and the residual."""

from __future__ import annotations

from typing import Any

import numpy as np

from physmend.explain.clock import axis
from physmend.problem import Problem
from physmend.simulate import Trajectories


def plot_experiment(problem: Problem, t: np.ndarray, traj: Trajectories, b: int) -> Any:
    """Measured vs simulated outputs and the residual for batch element ``b`` (``traj`` on the
    time grid ``t (T,)``): one row per output, a matplotlib figure."""
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
