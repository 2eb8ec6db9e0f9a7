"""Which inputs the kept corrections depend on: the inputs passed on to symbolic regression.

Jacobian of the kept corrections with respect to every network input along the training
trajectories (``torch.func``, :func:`physmend.ude.analysis.input_jacobian`), each column scaled by
its input's spread; inputs ranked by mean absolute sensitivity; the top k (or the names given) are
passed on. Along training trajectories some inputs move together (an air temperature and the wall
surface layers beside it correlate at r > 0.98), and one network may lean on any of them: the data
cannot tell them apart. Inputs correlated at ``|r| >= group_r`` with a representative are therefore
ranked as one group, by the sensitivity along their common direction; a measured quantity
represents its group (its values are known, a hidden state's are simulated), and the
representatives of the top k groups are passed on. ``group_r=None`` ranks single inputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Sensitivity:
    """What the sensitivity found: ``kept`` (the corrections), ``inputs`` (the network's inputs),
    ``ranking`` (``(input, score)`` best first), ``grouped`` (``(group, score)`` best first),
    ``chosen`` (the inputs passed on) and ``how`` (the rule that chose them, in words), ``matrix``
    (``(len(kept), len(inputs))`` mean scaled sensitivity, each output's maximum 1) and ``group_r``."""

    kept: list[str]
    inputs: list[str]
    ranking: list[tuple[str, float]]
    grouped: list[tuple[Any, float]]
    chosen: list[str]
    how: str
    matrix: np.ndarray
    group_r: float | None

    def record(self) -> dict[str, Any]:
        """The findings, JSON-ready."""
        return {"ranking": self.ranking, "chosen": self.chosen, "kept": self.kept, "inputs": self.inputs,
                "groups": [{"representative": g.representative, "members": g.members, "score": sc}
                           for g, sc in self.grouped],
                "matrix": self.matrix.tolist()}


def input_sensitivity(hybrid: Any, problem: Any, work: Any, *, max_rows: int, top_k: int, group_r: float | None,
                      names: list[str] | None = None) -> Sensitivity:
    """Rank the inputs of ``hybrid`` (trained on ``problem``; ``work``: its configuration) by the
    sensitivity of its kept corrections (at most ``max_rows`` samples of the Jacobian) and choose
    those passed on: ``names`` where given (inputs of the network: checked by the caller), else the
    representatives of the top ``top_k`` groups (``group_r`` given) or the top ``top_k`` inputs."""
    from physmend.ude.analysis import group_inputs, input_jacobian, rank_groups, rank_inputs, training_trajectories
    from physmend.ude.warmstart import measured_states

    kept = [n for n, m in zip(hybrid.spec.corrected, hybrid.out_mask.tolist()) if m > 0]
    traj = training_trajectories(hybrid, problem, work)
    jac = input_jacobian(hybrid, traj, max_rows=max_rows)
    ranking = rank_inputs(hybrid, jac, kept)
    measured = [problem.model.state_names[i] for _, i in measured_states(problem)]
    groups = group_inputs(hybrid, traj, measured, float(group_r) if group_r is not None else 1.1, [n for n, _ in ranking])
    grouped = rank_groups(hybrid, jac, groups, kept)
    if names:
        chosen = list(names)
        how = "chosen by name (sensitivity.inputs)"
    elif group_r is not None:
        chosen = [g.representative for g, _ in grouped[:top_k]]
        how = f"representatives of the top {top_k} groups (|r| >= {float(group_r):g})"
    else:
        chosen = [n for n, _ in ranking[:top_k]]
        how = f"top {top_k} by sensitivity"
    rows = [hybrid.spec.corrected.index(k) for k in kept]
    mag = jac[:, rows].abs().mean(0)
    mag = (mag / mag.amax(-1, keepdim=True).clamp_min(1e-300)).numpy()
    return Sensitivity(kept, list(hybrid.spec.input_names), ranking, grouped, chosen, how, mag, group_r)


def heatmap(found: Sensitivity) -> Any:
    """The sensitivity matrix (inputs × kept corrections), the inputs passed on starred."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    inputs, outputs, top = found.inputs, found.kept, found.chosen
    fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(inputs)), 1.2 + 0.5 * len(outputs)))
    im = ax.imshow(found.matrix, aspect="auto", cmap="viridis")
    ax.set_xticks(range(len(inputs)), [("★ " if n in top else "") + n for n in inputs], rotation=90, fontsize=7)
    ax.set_yticks(range(len(outputs)), outputs, fontsize=8)
    fig.colorbar(im, ax=ax, label="mean |d correction / d input| · std(input), per output max = 1")
    ax.set_title("sensitivity of the kept corrections (★: passed to symbolic regression)")
    fig.tight_layout()
    return fig


def report(found: Sensitivity, source: str) -> str:
    """The Markdown the sensitivity stage prints (``source``: ``<stage> run <id>``)."""
    chosen, grouped, group_r = found.chosen, found.grouped, found.group_r
    lines = [f"# physmend sensitivity — source {source}", "",
             f"Kept corrections: {', '.join(found.kept)}. Inputs ranked by mean |∂correction/∂input|·std(input):", ""]
    lines += [f"{i + 1:3d}. {'★' if n in chosen else ' '} {n}  {s:.3f}" for i, (n, s) in enumerate(found.ranking[:12])]
    if group_r is not None and any(len(g.members) > 1 for g, _ in grouped[:8]):  # else the same list again
        lines += ["", f"Ranked as groups of inputs that move together (|r| >= {float(group_r):g} along the training "
                  "trajectories), by the sensitivity along their common direction:", ""]
        for i, (g, sc) in enumerate(grouped[:8]):
            others = f"  (with {', '.join(g.members[1:])})" if len(g.members) > 1 else ""
            lines.append(f"{i + 1:3d}. {'★' if g.representative in chosen else ' '} {g.representative}  {sc:.3f}{others}")
    lines += ["", f"Passed to symbolic regression ({found.how}): {', '.join(chosen)}"]
    return "\n".join(lines)
