"""Sweep throughput: ``physmend sweep`` in a temporary folder with its own MLflow and Optuna stores."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

STUDY = "bench"


def physmend_cli() -> list[str]:
    """The ``physmend`` console script of this interpreter's environment (or ``python -m`` fallback)."""
    script = Path(sys.executable).parent / "physmend"
    return [str(script)] if script.exists() else [sys.executable, "-c", "import sys; from physmend.cli import main; sys.exit(main())"]


def config_has(key: str, overrides: Sequence[str]) -> bool:
    """Whether the composed config has ``key`` (e.g. ``sweep.workers``, which a trainer may add)."""
    from omegaconf import OmegaConf

    from _common import compose_config

    return OmegaConf.select(compose_config(overrides), key, default=None) is not None


def run(n_trials: int, *, workers: int, extra: Sequence[str], keep: bool, timeout_s: float) -> dict[str, Any]:
    """Run a sweep of ``n_trials`` trials; throughput in fully trained (COMPLETE) trials per hour.

    ``workers`` > 1: passed as ``sweep.workers`` when the config has that key, otherwise that many
    ``physmend sweep`` processes share the study (physmend's documented way to parallelise).
    """
    tmp = Path(tempfile.mkdtemp(prefix="physmend-bench-sweep-"))
    overrides = [f"sweep.n_trials={n_trials}", f"sweep.study_name={STUDY}", "sweep.progress=false",
                 f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.optuna_storage=sqlite:///{tmp}/optuna.db", *extra]
    native = workers > 1 and config_has("sweep.workers", overrides)
    if native:
        overrides.append(f"sweep.workers={workers}")
    procs = 1 if native else max(1, workers)
    cmd = [*physmend_cli(), "sweep", *overrides]
    start = time.perf_counter()
    logs = [open(tmp / f"worker{i}.log", "w") for i in range(procs)]  # noqa: SIM115 - closed below
    running = []
    for i in range(procs):
        running.append(subprocess.Popen(cmd, cwd=tmp, stdout=logs[i], stderr=subprocess.STDOUT))
        if i == 0 and procs > 1:
            time.sleep(5.0)  # let the first worker create the stores and the study
    codes = wait_all(running, start + timeout_s)
    wall = time.perf_counter() - start
    for f in logs:
        f.close()
    result = {"wall_s": wall, "n_trials": n_trials, "workers": workers, "processes": procs,
              "exit_codes": codes, "command": " ".join(cmd[-len(overrides) - 1:]), **study_counts(tmp)}
    if any(c != 0 for c in codes):
        result["log_tail"] = (tmp / "worker0.log").read_text()[-3000:]
    hours = wall / 3600.0
    result["complete_per_hour"] = result["complete"] / hours if hours > 0 else float("nan")
    result["trials_per_hour"] = (result["complete"] + result["pruned"] + result["failed"]) / hours if hours > 0 else float("nan")
    if keep:
        result["folder"] = str(tmp)
    else:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def wait_all(procs: list[subprocess.Popen], deadline: float) -> list[int | None]:
    """Exit codes of ``procs``; those still running at ``deadline`` (perf_counter s) are killed (None)."""
    codes: list[int | None] = []
    for p in procs:
        try:
            codes.append(p.wait(timeout=max(deadline - time.perf_counter(), 0.1)))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            codes.append(None)
    return codes


def study_counts(folder: Path) -> dict[str, Any]:
    """Trial states, best value and mean COMPLETE trial duration (s) from the study's Optuna storage."""
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.load_study(study_name=STUDY, storage=f"sqlite:///{folder}/optuna.db")
    except Exception as exc:  # noqa: BLE001 - no study: the sweep failed before creating it
        return {"complete": 0, "pruned": 0, "failed": 0, "best_val_rmse": float("nan"), "error": str(exc)[:300]}
    trials = study.get_trials(deepcopy=False)
    done = [t for t in trials if t.state == TrialState.COMPLETE]
    durations = [(t.datetime_complete - t.datetime_start).total_seconds() for t in done if t.datetime_complete and t.datetime_start]
    return {
        "complete": len(done),
        "pruned": sum(t.state == TrialState.PRUNED for t in trials),
        "failed": sum(t.state == TrialState.FAIL for t in trials),
        "best_val_rmse": min((t.value for t in done if t.value is not None), default=float("nan")),
        "mean_complete_trial_s": sum(durations) / len(durations) if durations else float("nan"),
    }
