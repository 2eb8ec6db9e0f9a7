"""The study loop: ask a trial (or a group, :mod:`physmend.sweep.group`), compose, train, log the
child run, tell Optuna; prune, stop on failures, mark stale trials (:mod:`physmend.sweep.run` drives it).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.config import ConfigError
from physmend.sweep.child import child_run, kill_child, mark_child, record_restart
from physmend.sweep.configs import TrialConfigs
from physmend.sweep.ctrl_c import check as check_ctrl_c
from physmend.sweep.group import StackedTrials
from physmend.sweep.outcome import Outcome
from physmend.sweep.report import EpochProgress, Reporter, _log_result, _say, _show
from physmend.sweep.restart import interrupted, one_line
from physmend.sweep.settings import Settings
from physmend.sweep.space import SearchSpace
from physmend.sweep.storage import REASON_ATTR, RUN_ID_ATTR, WORKER_ATTR, _uncounted, asking, tally
from physmend.sweep.workers import Heartbeat, is_stale, this_worker
from physmend.tracking.marks import RUN_NAME_TAG, trial_name

if TYPE_CHECKING:
    import optuna
    from physmend.problem import Problem
    from physmend.tracking import Store


DECISION_POLL_S = 0.25
"""Seconds between looks at the study while a worker waits for the budget's decision."""


@dataclass
class Sweep(StackedTrials):
    """Everything one worker process needs to run trials of a study."""

    cfg: DictConfig
    settings: Settings
    space: SearchSpace
    study: Any
    storage: Any
    store: "Store"
    parent_run_id: str
    configs: TrialConfigs
    train: Callable[..., Any]
    me: dict[str, Any] = field(default_factory=this_worker)
    failures_in_a_row: int = 0
    bar: Any = None  # the progress bar of the running loop (messages are written above it)
    target: int | None = None  # trials the study has in the end (sweep.n_trials, or the budget's decision)
    budget_line: str = ""  # the budget's decision, for the summary
    progress: Any = None  # EpochProgress: the bar's "trial 3 epoch 20/120" while a trial trains
    #: the caller's work for after the sweep, run once where this worker would otherwise only wait for
    #: the others' trials (:meth:`idle`); None: nothing, or done
    meanwhile: Callable[[], None] | None = None

    @property
    def n_trials(self) -> int:
        """Trials the study should have in the end: ``sweep.n_trials``, or with ``sweep.budget`` the
        budget's decision once made (until then the minimum, ``sweep.n_trials``)."""
        return self.settings.n_trials if self.target is None else self.target

    def apply_budget(self, bar: Any) -> None:
        """With ``sweep.budget``: once ``sweep.n_trials`` trials reached a verdict, decide how many the
        study has in the end (:mod:`physmend.sweep.budget`), once per study (stored with it; a
        resumed sweep and other workers use the stored decision)."""
        from physmend.sweep.budget import BUDGET_ATTR, at_once, wall_span
        from physmend.sweep.storage import _uncounted

        budget = self.settings.budgeted
        if budget is None or self.target is not None:
            return
        stored = self.study.user_attrs.get(BUDGET_ATTR)
        if not budget.matches(stored):
            finished = [t for t in self.study.get_trials(deepcopy=False) if t.state.is_finished() and not _uncounted(t)]
            if len(finished) < budget.min_trials:
                return
            finished = sorted(finished, key=lambda t: t.number)[: budget.min_trials]
            stored = budget.decision(wall_span(finished), len(finished), at_once(finished))
            self.study.set_user_attr(BUDGET_ATTR, stored)
            stored = self.study.user_attrs.get(BUDGET_ATTR, stored)  # another worker may have decided first
        self.target = int(stored["trials"])
        self.budget_line = budget.describe(stored)
        if bar is not None:
            bar.total = self.target
            _say(bar, self.budget_line)

    # ---- the loop
    def loop(self, bar: Any) -> list[Outcome]:
        """Ask, train and tell until the study has ``n_trials`` trials or time runs out."""
        start = time.monotonic()
        self.bar = bar
        self.progress = EpochProgress(bar, int(OmegaConf.select(self.cfg, "train.epochs", default=0) or 0))
        outcomes: list[Outcome] = []
        while True:
            check_ctrl_c()  # one that Python dropped in a finaliser (physmend.sweep.ctrl_c)
            self.fail_stale_trials(bar)
            counts = tally(self.study.get_trials(deepcopy=False))
            self.apply_budget(bar)
            _show(bar, counts)
            timed_out = self.settings.timeout is not None and time.monotonic() - start >= self.settings.timeout
            if counts.counted + counts.running >= self.n_trials:
                if timed_out or not self._decision_pending(counts):
                    break
                # the budget decides when the running trials end, and may ask for more: this worker
                # waits to run its share of them instead of leaving them to the others
                self.idle()
                time.sleep(DECISION_POLL_S)
                continue
            if timed_out:
                _say(bar, f"sweep.timeout of {self.settings.timeout:g} s reached; no new trial is started")
                break
            if self.settings.group > 1:
                batch = self.trial_group(bar, self.group_size(counts))
                if batch is None:  # surplus (see below)
                    continue
                for outcome in batch:
                    outcomes.append(outcome)
                    self._after(outcome, bar)
                continue
            outcome = self.one_trial(bar)
            if outcome is None:
                # surplus: another worker asked for the last trial at the same moment. The top of the
                # loop decides: the end, or (the budget's decision pending, a trial ahead interrupted)
                # wait or ask again; leaving here would leave the budget's extra trials to the others
                continue
            outcomes.append(outcome)
            self._after(outcome, bar)
        return outcomes

    def idle(self) -> None:
        """Run :attr:`meanwhile` once, now that this worker waits for trials running elsewhere. Its
        failure is not the sweep's: the stage it prepares does the same work again and reports it."""
        work, self.meanwhile = self.meanwhile, None
        if work is not None:
            try:
                work()
            except Exception:  # noqa: BLE001, S110 - see the docstring
                pass

    def _decision_pending(self, counts: Any) -> bool:
        """Whether ``sweep.budget``'s decision is still to come while the minimum's last trials run
        (in other workers): it may ask for more trials than the minimum."""
        return self.settings.budgeted is not None and self.target is None and counts.running > 0

    def _after(self, outcome: Outcome, bar: Any) -> None:
        if outcome.state == "FAIL":
            _say(bar, f"trial {outcome.number} failed: {one_line(outcome.reason, 1000)}")
            self.failures_in_a_row += 1
            limit = self.settings.max_failures_in_a_row
            if limit and self.failures_in_a_row >= limit:
                raise ConfigError(
                    f"{self.failures_in_a_row} trials in a row failed (sweep.max_failures_in_a_row = {limit}); "
                    f"the last: trial {outcome.number}: {outcome.reason}. Check the configuration and the search "
                    f"space {self.space.label}; resume with the same command"
                )
        else:
            self.failures_in_a_row = 0

    def one_trial(self, bar: Any) -> Outcome | None:
        """Ask for one trial and run it; ``None`` when the trial turned out to be surplus."""
        from optuna.trial import TrialState

        n_before = len(self.study.get_trials(deepcopy=False))
        self.study.sampler = self.settings.sampler_for(n_before)
        with asking(self.storage):
            trial = self.study.ask()
        trial.set_user_attr(WORKER_ATTR, self.me)
        if self._surplus(trial):
            trial.set_user_attr(REASON_ATTR, "surplus")
            self.study.tell(trial, state=TrialState.FAIL)
            return None
        try:
            with Heartbeat(trial, self.settings.heartbeat_interval):
                outcome = self.run_trial(trial)
        except KeyboardInterrupt:
            trial.set_user_attr(REASON_ATTR, "interrupted")
            self.study.tell(trial, state=TrialState.FAIL)
            raise
        self.tell(trial, outcome)
        return outcome

    def _surplus(self, trial: "optuna.Trial") -> bool:
        """Whether trials numbered before this one already fill ``n_trials`` (a race between workers)."""
        from optuna.trial import TrialState

        ahead = [
            t for t in self.study.get_trials(deepcopy=False)
            if t.number < trial.number and (t.state == TrialState.RUNNING or (t.state.is_finished() and not _uncounted(t)))
        ]
        return len(ahead) >= self.n_trials

    def tell(self, trial: "optuna.Trial", outcome: Outcome) -> None:
        from optuna.trial import TrialState

        try:
            if outcome.state == "COMPLETE":
                self.study.tell(trial, outcome.value)
            elif outcome.state == "PRUNED":
                self.study.tell(trial, state=TrialState.PRUNED)
            else:
                trial.set_user_attr(REASON_ATTR, outcome.reason[:2000])
                self.study.tell(trial, state=TrialState.FAIL)
        except (ValueError, RuntimeError) as exc:  # finished meanwhile, e.g. judged stale by another worker
            message = f"trial {trial.number}: could not record the result in the study: {exc}"
            if self.bar is not None:
                _say(self.bar, message)  # above the progress bar, not over its line
            else:
                sys.stderr.write(message + "\n")

    # ---- one trial
    def run_trial(self, trial: "optuna.Trial") -> Outcome:
        """Compose, train and log one trial as a child run; exceptions from training become FAIL."""
        values = self.space.suggest(trial)
        try:
            cfg = self.configs.config(values)
            problem = self.configs.problem(values, cfg)
        except Exception as exc:  # noqa: BLE001 - a bad trial config fails the trial, not the sweep
            return Outcome(trial.number, "FAIL", reason=f"{type(exc).__name__}: {exc}")
        holder: dict[str, str] = {}
        try:
            return self._train_logged(trial, values, cfg, problem, holder)
        except Exception as exc:  # noqa: BLE001 - diverged, solver failure, anything: FAIL, sweep goes on
            if interrupted(exc):  # Ctrl-C inside a library's import, C code or a store write
                kill_child(self.store, holder.get("run_id"), "interrupted (KeyboardInterrupt)")
                raise KeyboardInterrupt from exc
            mark_child(self.store, holder.get("run_id"), "FAIL")
            return Outcome(trial.number, "FAIL", run_id=holder.get("run_id"), reason=f"{type(exc).__name__}: {exc}")
        except KeyboardInterrupt:
            kill_child(self.store, holder.get("run_id"), "interrupted (KeyboardInterrupt)")
            raise

    def _train_logged(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, problem: "Problem", holder: dict[str, str]) -> Outcome:
        import mlflow
        import optuna

        from physmend.sweep.restart import Attempts
        from physmend.tracking import selection as sel

        with child_run(self.store, self.study.study_name, self.parent_run_id, trial, values, cfg, holder) as run_:
            reporter = Reporter(trial, run_, self.settings.pruned_because, on_epoch=self.progress)
            if self.progress is not None:
                self.progress.start([trial.number])
            attempts = Attempts(cfg, self.settings.restarts)
            while True:
                try:
                    result = self.train(attempts.current, problem, report=reporter)
                    value = float(result.val_rmse)
                    if not math.isfinite(value):
                        raise FloatingPointError(f"the final val.rmse is not finite ({value})")
                    break
                except optuna.TrialPruned as exc:
                    run_.set_tags({sel.TRIAL_STATE_TAG: "PRUNED", "physmend.pruned": str(exc) or "pruned"})
                    mlflow.end_run("KILLED")
                    return Outcome(trial.number, "PRUNED", value=reporter.last_value, run_id=run_.run_id,
                                   reason=str(exc), restarts=attempts.restarts)
                except Exception as exc:  # noqa: BLE001 - divergence restarts the trial; anything else FAILs it
                    if not attempts.restart_after(exc):
                        raise attempts.final(exc) from None
                    record_restart(trial, attempts, run_, self.bar, self.settings.restarts)
                    reporter = reporter.restarted()
            _log_result(run_, result, step=reporter.last_epoch + 1, figures=self.settings.figures)
            run_.set_tags({sel.TRIAL_STATE_TAG: "COMPLETE", RUN_NAME_TAG: trial_name(trial.number, value)})
        return Outcome(trial.number, "COMPLETE", value=value, run_id=run_.run_id, restarts=attempts.restarts)

    # ---- stale trials
    def fail_stale_trials(self, bar: Any) -> None:
        """Mark RUNNING trials whose worker is gone FAIL (interrupted), their child runs KILLED."""
        from optuna.trial import TrialState

        now = time.time()
        for t in self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            if not is_stale(t, now=now, stale_after=self.settings.stale_after, me=self.me):
                continue
            worker = t.user_attrs.get(WORKER_ATTR) or {}
            try:
                trial_id = self.storage.get_trial_id_from_study_id_trial_number(
                    self.storage.get_study_id_from_name(self.study.study_name), t.number
                )
                self.storage.set_trial_user_attr(trial_id, REASON_ATTR, "interrupted")
                self.study.tell(t.number, state=TrialState.FAIL)
            except Exception:  # noqa: BLE001 - another worker got there first
                continue
            where = f"{worker.get('host', '?')}:{worker.get('pid', '?')}"
            kill_child(self.store, t.user_attrs.get(RUN_ID_ATTR), f"interrupted: its worker {where} stopped")
            _say(bar, f"trial {t.number} was left running by worker {where}, which stopped; marked FAIL (interrupted)")
