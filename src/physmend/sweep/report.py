"""Progress and results: the per-epoch reporter (metrics, pruning), a trial's logged result, the
progress bar's lines and the sweep's closing summary. Imports storage.
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from physmend.sweep.space import hydra_value
from physmend.sweep.storage import Tally

if TYPE_CHECKING:
    from physmend.sweep.loop import Sweep
    import optuna


class Reporter:
    """The ``report`` callback of one trial: per-epoch metrics to MLflow, pruning via Optuna."""

    def __init__(self, trial: "optuna.Trial", run_: Any, because: str) -> None:
        """``run_`` None: metrics are kept in ``buffered`` (a stacked trial's run is written afterwards);
        ``because``: how the pruner compares (:attr:`Settings.pruned_because`, ends a pruned trial's message)."""
        self.trial, self.run_, self.because = trial, run_, because
        self.last_epoch = 0
        self.last_value: float | None = None
        self.buffered: list[tuple[int, dict[str, float]]] = []

    def __call__(self, epoch: int, metrics: dict[str, float]) -> None:
        import optuna

        epoch = int(epoch)
        self.last_epoch = max(self.last_epoch, epoch)
        finite = {k: float(v) for k, v in metrics.items() if k != "epoch" and v is not None and math.isfinite(float(v))}
        if self.run_ is None:
            self.buffered.append((epoch, finite))
        else:
            self.run_.log_metrics(finite, step=epoch)
        value = finite.get("val.rmse")
        if value is None:
            return
        self.last_value = value
        self.trial.report(value, epoch)
        if self.trial.should_prune():
            raise optuna.TrialPruned(f"pruned at epoch {epoch}: val.rmse {value:.4g} is {self.because}")



def _log_result(run_: Any, result: Any, *, step: int, figures: bool = True) -> None:
    """Final metrics (at ``step``, after the per-epoch ones), model files, history, figures (``figures``)."""
    import matplotlib.pyplot as plt
    import mlflow

    metrics = {k: float(v) for k, v in result.metrics.items() if v is not None and math.isfinite(float(v))}
    metrics["val.rmse"] = float(result.val_rmse)
    run_.log_metrics(metrics, step=step)
    with tempfile.TemporaryDirectory(prefix="physmend-artifacts-") as tmp:
        for rel, content in result.artifacts.items():
            path = Path(tmp) / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, bytes):
                path.write_bytes(content)
            else:
                path.write_text(content)
        if result.artifacts:
            mlflow.log_artifacts(tmp)
    run_.log_json(result.history, "history.json")
    for rel, fig in (result.figures or {}).items():
        if figures:
            run_.log_figure(fig, rel)
        plt.close(fig)



def _say(bar: Any, message: str) -> None:
    """A line on stderr above the progress bar."""
    bar.write(message, file=sys.stderr)



def _show(bar: Any, counts: Tally) -> None:
    bar.n = min(counts.counted, bar.total) if bar.total else counts.counted
    if counts.best_value is not None:
        bar.set_postfix_str(f"best val.rmse {counts.best_value:.4g} (trial {counts.best_number})", refresh=False)
    bar.refresh()



def summary(sweep: Sweep, counts: Tally) -> str:
    """What the sweep found and the exact next commands."""
    from physmend.tracking import selection as sel

    parent = sweep.store.client.get_run(sweep.parent_run_id)
    tags = parent.data.tags
    lines = [
        f"sweep {sweep.study.study_name} (space {sweep.space.label}), run {sweep.parent_run_id}:",
        f"  {counts.counted} of {sweep.settings.n_trials} trials: {counts.complete} complete, {counts.pruned} pruned, "
        f"{counts.failed} failed" + (f" ({counts.uncounted} interrupted, not counted)" if counts.uncounted else "")
        + (f"; {counts.running} still running in other workers" if counts.running else ""),
    ]
    best = tags.get(sel.BEST_TAG)
    if best is None or counts.best_value is None:
        lines += ["  no trial finished training, so nothing is selected.",
                  "next: look at the failures with `physmend runs`, then change the configuration or the search space"]
        return "\n".join(lines)
    frozen = next(t for t in sweep.study.get_trials(deepcopy=False) if t.number == counts.best_number)
    params = " ".join(f"{k}={hydra_value(v)}" for k, v in frozen.params.items())
    lines.append(f"  best: trial {counts.best_number}, val.rmse {counts.best_value:.6g}, run {best}")
    lines.append(f"        {params}")
    selected, by = tags.get(sel.SELECTED_TAG), tags.get(sel.SELECTED_BY_TAG)
    if selected == best:
        lines.append(f"  selected: {selected} (automatic: lowest val.rmse)")
    else:
        lines.append(f"  selected: {selected} (chosen by {by}; kept — `physmend select {best}` takes the best)")
    lines += [
        "next:",
        "  physmend runs                  # every trial, the selection marked",
        "  physmend select RUN_ID         # choose another trial",
        "  physmend mask                  # keep only the corrections that matter (on the selected trial)",
    ]
    return "\n".join(lines)
