"""Shared pieces of the benchmark harness: configuration, noise floor, stopping rule, machine facts.

Units: times in seconds (s), memory in MiB, RMSE in the outputs' own unit (degC for the cargo box).
"""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_EVAL_EVERY = 5  # epochs between whole-trajectory evaluations (both methods)


class TargetReached(Exception):
    """Raised from the trainer's report callback to stop at the first evaluation meeting the target."""


class TimeCapReached(Exception):
    """Raised when a timed run exceeds its wall-clock cap (s)."""


@dataclass
class Target:
    """The stopping rule: stop at the first evaluation with ``val.rmse**2 <= factor * noise**2``.

    ``noise`` is the pooled (RMS) sensor-noise estimate in output units; ``rmse`` the resulting
    threshold on ``val.rmse`` (same unit).
    """

    noise: float
    factor: float = 2.0

    @property
    def rmse(self) -> float:
        return float(np.sqrt(self.factor) * self.noise)

    def met(self, val_rmse: float) -> bool:
        return bool(np.isfinite(val_rmse) and val_rmse**2 <= self.factor * self.noise**2)


def compose_config(overrides: Sequence[str] = ()) -> Any:
    """The composed physmend config (defaults: the bundled cargo-box example) plus ``overrides``."""
    from physmend.config import compose

    return compose(list(overrides))


def load(overrides: Sequence[str] = ()) -> tuple[Any, Any]:
    """``(cfg, problem)`` for ``overrides``; ``load_problem`` also sets torch to ``cfg.threads`` threads."""
    from physmend.problem import load_problem

    cfg = compose_config(overrides)
    return cfg, load_problem(cfg)


def noise_floor(problem: Any) -> dict[str, Any]:
    """Sensor-noise estimate per training experiment and output (training samples only), pooled by RMS.

    Uses :func:`physmend.explain.residuals.noise_floor` (second differences, MAD). When the outputs
    have different units, each estimate is divided by that output's spread over the training
    samples, as :func:`physmend.ude.train.evaluate` scales ``val.rmse``; otherwise output units.
    """
    from physmend.explain.residuals import noise_floor as estimate

    model = problem.model
    outputs = list(model.output_names)
    train = problem.by_role("train")
    units = {model.units.get(o, "") for o in outputs}
    per: dict[str, float] = {}
    samples: list[np.ndarray] = []
    for e in train:
        keep = e.obs_time < float(e.split_time) if e.split_time is not None else np.ones(e.obs_time.shape, bool)
        samples.append(e.obs[keep])
        for j, out in enumerate(outputs):
            per[f"{e.id}.{out}"] = estimate(e.obs_time[keep], e.obs[keep, j])
    scale = {o: 1.0 for o in outputs}
    if len(units) > 1:
        stacked = np.concatenate(samples)
        scale = {o: float(max(np.nanstd(stacked[:, j], ddof=1), 1e-12)) for j, o in enumerate(outputs)}
    scaled = [v / scale[k.split(".", 1)[1]] for k, v in per.items() if np.isfinite(v)]
    pooled = float(np.sqrt(np.mean(np.square(scaled)))) if scaled else float("nan")
    return {"per_series": per, "pooled": pooled, "scaled_by_spread": len(units) > 1}


def peak_rss_mib() -> float:
    """Peak resident set size of this process so far (MiB; Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict[str, Any]:
    """CPU model, core counts, load, library versions and the checkout's git commit."""
    import torch

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "loadavg_1m": os.getloadavg()[0],
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git": git_revision(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def git_revision() -> str:
    """``<short commit>`` of the checkout, ``+dirty`` when tracked files under src/ differ from it."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "src"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
