"""The model as written and the corrected model simulated whole on every experiment, and their
fits side by side: RMSE per experiment and output before and after, against the sensor noise."""

from __future__ import annotations

from typing import Any

import torch


def simulate(problem: Any, cfg: Any) -> tuple[Any, Any, list[Any]]:
    """Every experiment of ``problem`` simulated whole (the batch, the trajectories), and where the
    model diverges: a model that blows up (the model as written, or a corrected one on a held-out
    experiment) is held inside the box of its records from then on and reported, never a failed
    stage (:func:`physmend.diagnosis.simulate_as_written`)."""
    from physmend.simulate import make_batch
    from physmend.diagnosis import simulate_as_written

    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    traj, diverged = simulate_as_written(problem, batch, cfg)
    return batch, traj, list(diverged)


def rmse(err: torch.Tensor) -> float:
    """Root mean square of the finite entries of ``err`` (NaN where none is)."""
    e = err[torch.isfinite(err)]
    return float(e.pow(2).mean().sqrt()) if e.numel() else float("nan")


def fit_rows(problem: Any, batch: Any, before: Any, after: Any) -> list[dict[str, Any]]:
    """One row per experiment and output of ``problem``: ``before``/``after`` (the RMSE of the
    trajectories ``before`` and ``after`` against the records of ``batch``), ``noise`` (an estimate
    of the sensor noise) and ``improvement`` (before / after)."""
    from physmend.explain.residuals import noise_floor

    rows = []
    for b, e in enumerate(problem.experiments):
        for j, out in enumerate(problem.model.output_names):
            y = batch.obs[:, b, j]
            r0, r1 = rmse(before.outputs[:, b, j] - y), rmse(after.outputs[:, b, j] - y)
            m = torch.isfinite(y)
            noise = noise_floor(batch.t[m].numpy(), y[m].numpy())
            rows.append({"experiment": e.id, "role": e.role, "output": out, "before": r0, "after": r1,
                         "noise": noise, "improvement": r0 / r1 if r1 > 0 else float("inf")})
    return rows
