"""Progress and results: the per-epoch reporter (metrics, pruning), a trial's logged result, the
progress bar's lines and the sweep's closing summary. Imports storage.
"""

from __future__ import annotations

import math
import sys
import tempfile
from pathlib import Path
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from physmend.sweep.space import hydra_value
from physmend.sweep.storage import Tally

if TYPE_CHECKING:
    from physmend.sweep.loop import Sweep
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



def divergence(trials: Any, restarts: int) -> str:
    """The sweep's divergence rate, one line: of the trials that reached a verdict, how many diverged
    and were restarted (``sweep.restarts`` at most each), how many of those still failed, and how
    many failed in all (each failure's reason is on its own line above and in its run)."""
    from optuna.trial import TrialState

    from physmend.sweep.restart import RESTARTS_ATTR
    from physmend.sweep.storage import _uncounted

    counted = [t for t in trials if t.state.is_finished() and not _uncounted(t)]
    again = [t for t in counted if int(t.user_attrs.get(RESTARTS_ATTR, 0) or 0) > 0]
    lost = [t for t in again if t.state == TrialState.FAIL]
    failed = sum(t.state == TrialState.FAIL for t in counted)
    if not again:
        return (f"divergence: no trial of {len(counted)} diverged" if not failed
                else f"divergence: no trial of {len(counted)} was restarted; {failed} failed (reasons above)")
    return (f"divergence: {len(again)} of {len(counted)} trials diverged and were restarted (up to {restarts}×: "
            f"smaller steps, then no warm start): {len(again) - len(lost)} then trained to the end or were "
            f"pruned, {len(lost)} failed; {failed} of {len(counted)} failed in all")


def summary(sweep: Sweep, counts: Tally) -> str:
    """What the sweep found and the exact next commands."""
    from physmend.tracking import selection as sel

    parent = sweep.store.client.get_run(sweep.parent_run_id)
    tags = parent.data.tags
    lines = [
        f"sweep {sweep.study.study_name} (space {sweep.space.label}), run {sweep.parent_run_id}:",
        f"  {counts.counted} of {sweep.n_trials} trials: {counts.complete} complete, {counts.pruned} pruned, "
        f"{counts.failed} failed" + (f" ({counts.uncounted} interrupted, not counted)" if counts.uncounted else "")
        + (f"; {counts.running} still running in other workers" if counts.running else ""),
    ]
    if sweep.budget_line:
        lines.append(f"  {sweep.budget_line}")
    lines.append(f"  {divergence(sweep.study.get_trials(deepcopy=False), sweep.settings.restarts)}")
    best = tags.get(sel.BEST_TAG)
    if best is None or counts.best_value is None:
        lines += ["  no trial finished training, so nothing is selected.",
                  "next: look at the failures with `physmend runs`, then change the configuration or the search space"]
        return "\n".join(lines)
    frozen = next(t for t in sweep.study.get_trials(deepcopy=False) if t.number == counts.best_number)
    params = " ".join(f"{k}={hydra_value(v)}" for k, v in frozen.params.items())
    so_far = " so far" if counts.running else ""  # other workers still train: nothing here is final yet
    lines.append(f"  best{so_far}: trial {counts.best_number}, val.rmse {counts.best_value:.6g}, run {best}")
    lines.append(f"        {params}")
    selected, by = tags.get(sel.SELECTED_TAG), tags.get(sel.SELECTED_BY_TAG)
    if selected == best:
        lines.append(f"  selected{so_far}: {selected} (automatic: lowest val.rmse)")
    else:
        lines.append(f"  selected{so_far}: {selected} (chosen by {by}; kept — `physmend select {best}` takes the best)")
    if counts.running:
        lines.append(f"  not final: {counts.running} trial(s) still running in other workers; the last worker to "
                     "finish records the final choice (`physmend runs` shows it)")
    lines += [
        "next:",
        "  physmend runs                  # every trial, the selection marked",
        "  physmend select RUN_ID         # choose another trial",
        "  physmend mask                  # keep only the corrections that matter (on the selected trial)",
    ]
    return "\n".join(lines)
