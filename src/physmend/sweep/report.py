"""Progress and results: the per-epoch reporter (metrics, pruning), a trial's logged result and the
progress bar's lines (the sweep's closing summary: :mod:`physmend.sweep.summary`).
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from physmend.sweep.ctrl_c import check as check_ctrl_c
from physmend.sweep.storage import Tally

if TYPE_CHECKING:
    import optuna


class Reporter:
    """The ``report`` callback of one trial: per-epoch metrics to MLflow, pruning via Optuna."""

    def __init__(self, trial: "optuna.Trial", run_: Any, because: str, *, step_offset: int = 0,
                 reported: int = -1, on_epoch: Callable[[int, int], None] | None = None) -> None:
        """``run_`` None: metrics are kept in ``buffered`` (a stacked trial's run is written afterwards);
        ``because``: how the pruner compares (:attr:`Settings.pruned_because`, ends a pruned trial's message).

        A restarted trial's reporter (:meth:`restarted`) logs its epochs after the earlier attempts'
        (``step_offset``: MLflow step of its epoch 0), and reports to Optuna only epochs past
        ``reported`` (the last epoch an earlier attempt reported: Optuna keeps one value per step)."""
        self.trial, self.run_, self.because = trial, run_, because
        self.step_offset = step_offset
        self.reported = reported
        self.last_epoch = step_offset
        self.last_value: float | None = None
        self.buffered: list[tuple[int, dict[str, float]]] = []
        self.on_epoch = on_epoch  # (trial number, epoch): the progress bar's "trial 3 epoch 12/40"

    def restarted(self) -> "Reporter":
        """The reporter of this trial's next attempt (a restart after divergence): its MLflow steps
        follow this attempt's, its buffered metrics are kept."""
        nxt = Reporter(self.trial, self.run_, self.because, step_offset=self.last_epoch + 1, reported=self.reported,
                       on_epoch=self.on_epoch)
        nxt.last_value, nxt.buffered = self.last_value, self.buffered
        return nxt

    def __call__(self, epoch: int, metrics: dict[str, float]) -> None:
        import optuna

        check_ctrl_c()  # one that Python dropped in a finaliser during this epoch (physmend.sweep.ctrl_c)
        epoch = int(epoch)
        if self.on_epoch is not None:
            self.on_epoch(self.trial.number, epoch)
        step = epoch + self.step_offset
        self.last_epoch = max(self.last_epoch, step)
        finite = {k: float(v) for k, v in metrics.items() if k != "epoch" and v is not None and math.isfinite(float(v))}
        if self.run_ is None:
            self.buffered.append((step, finite))
        else:
            self.run_.log_metrics(finite, step=step)
        value = finite.get("val.rmse")
        if value is None:
            return
        self.last_value = value
        if epoch <= self.reported:  # an earlier attempt reported this epoch: Optuna keeps the first value
            return
        self.reported = epoch
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
        bar.physmend_best = f"best val.rmse {counts.best_value:.4g} (trial {counts.best_number})"
        bar.set_postfix_str(bar.physmend_best, refresh=False)
    bar.refresh()


class EpochProgress:
    """The ``on_epoch`` of every :class:`Reporter` of one worker: the bar's postfix says which trials
    train and their epoch (``trials 5–9 epoch 12/40 · best val.rmse …``), redrawn at most every
    ``interval`` s (so a log file gets no line per epoch)."""

    def __init__(self, bar: Any, epochs: int, interval: float = 0.5) -> None:
        self.bar, self.epochs, self.interval = bar, int(epochs), interval
        self.last = 0.0
        self.training: dict[int, int] = {}  # trial number -> its latest epoch

    def start(self, numbers: list[int]) -> None:
        """A trial or a stack of trials begins."""
        self.training = {n: 0 for n in numbers}

    def __call__(self, number: int, epoch: int) -> None:
        import time

        self.training[number] = epoch
        now = time.monotonic()
        if self.bar is None or getattr(self.bar, "disable", True) or now - self.last < self.interval:
            return
        self.last = now
        numbers = sorted(self.training)
        who = f"trial {numbers[0]}" if len(numbers) == 1 else f"trials {numbers[0]}–{numbers[-1]}"
        best = getattr(self.bar, "physmend_best", "")
        epoch = max(self.training.values())
        self.bar.set_postfix_str(f"{who} epoch {epoch}" + (f"/{self.epochs}" if epoch <= self.epochs else "")
                                 + (f" · {best}" if best else ""), refresh=True)
