"""The model as written against every experiment: simulated, analysed, summarised
(the diagnose stage's work)."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

import numpy as np

from physmend.diagnosis.analysis import analyse
from physmend.diagnosis.simulation import json_ready, simulate_as_written
from physmend.diagnosis.summary import summarise
from physmend.problem import Problem
from physmend.simulate import Trajectories, make_batch
from physmend.simulate.divergence import Divergence


def _quiet(what: str) -> AbstractContextManager[None]:
    return nullcontext()


@dataclass
class Diagnosis:
    """What the diagnosis found.

    ``traj``: the model as written on every experiment (batch element ``b`` = experiment ``b``) on
    the time grid ``t (T,)`` in the data's time unit; ``diverged``: where it diverges, earliest
    first; ``analysis``: the JSON-ready findings (:func:`~physmend.diagnosis.analysis.analyse`,
    with ``divergence`` where it diverges); ``summary``: the Markdown summary."""

    problem: Problem
    traj: Trajectories
    t: np.ndarray
    diverged: list[Divergence]
    analysis: dict[str, Any]
    summary: str

    def metrics(self) -> dict[str, float]:
        """``rmse.``/``bias.``/``noise.<experiment>.<output>``, ``diverges_at.<experiment>`` (the
        earliest output's) and ``max_rmse_to_noise``; finite values only."""
        metrics: dict[str, float] = {}
        for f in self.analysis["fits"]:
            key = f"{f['experiment']}.{f['output']}"
            metrics[f"rmse.{key}"] = f["rmse"]
            metrics[f"bias.{key}"] = f["bias"]
            metrics[f"noise.{key}"] = f["noise"]
        for d in self.diverged:
            metrics.setdefault(f"diverges_at.{d.experiment}", d.time)  # the earliest output of each experiment
        finite = [f["ratio_to_noise"] for f in self.analysis["fits"] if np.isfinite(f["ratio_to_noise"])]
        if finite:
            metrics["max_rmse_to_noise"] = max(finite)
        return {k: v for k, v in metrics.items() if np.isfinite(v)}

    def description(self) -> str | None:
        """One sentence for the run's description: where it diverges, or how far it misses the noise
        (None where no output has a noise estimate)."""
        worst = max(self.analysis["fits"], key=lambda f: f["rmse"] / f["noise"] if f["noise"] > 0 else 0.0, default=None)
        if self.diverged:
            d = self.diverged[0]
            how = "blows up in finite time" if d.blows_up else "grows without bound"
            return (f"The model as written diverges: {d.name} {how}, leaving the recorded range at "
                    f"t = {d.time:.4g} {self.problem.time_unit} (experiment {d.experiment}). Next: physmend sweep.")
        if worst is not None and worst["noise"] > 0:
            return (f"The model as written misses by up to {worst['rmse'] / worst['noise']:.1f}× the estimated sensor "
                    f"noise ({worst['output']}, experiment {worst['experiment']}). Next: physmend sweep.")
        return None


def diagnose(problem: Problem, cfg: Any, *,
             progress: Callable[[str], AbstractContextManager[Any]] = _quiet) -> Diagnosis:
    """Simulate the model as written of ``problem`` against every experiment (``cfg.simulate``) and
    locate the mismatch (``cfg.diagnose``); nothing is written. ``progress(what)``: a context shown
    while a step with no count runs."""
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with progress(f"diagnose: simulating {len(problem.experiments)} experiments as written"):
        traj, diverged = simulate_as_written(problem, batch, cfg)
    t = batch.t.cpu().numpy()
    with progress("diagnose: locating the mismatch"):
        analysis = analyse(problem, traj, t, cfg)
    if diverged:
        analysis["divergence"] = [json_ready(d) for d in diverged]
    return Diagnosis(problem, traj, t, diverged, analysis, summarise(problem, analysis, cfg))
