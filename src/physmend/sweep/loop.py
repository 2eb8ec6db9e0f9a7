"""The study loop: ask a trial (or a group), compose, train (alone or as one stack), log the child
run, tell Optuna; prune, stop on failures, mark stale trials (:mod:`physmend.sweep.run` drives it).
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.redact import redact
from physmend.config import ConfigError
from physmend.sweep.configs import TrialConfigs
from physmend.sweep.report import EpochProgress, Reporter, _log_result, _say, _show
from physmend.sweep.restart import RESTARTS_ATTR, interrupted, one_line
from physmend.sweep.settings import Settings, shape_keys
from physmend.sweep.space import SearchSpace
from physmend.sweep.storage import REASON_ATTR, RUN_ID_ATTR, Tally, WORKER_ATTR, _uncounted, tally
from physmend.sweep.workers import Heartbeat, _worker, is_stale
from physmend.tracking.marks import RUN_NAME_TAG, trial_name

if TYPE_CHECKING:
    import optuna
    from physmend.problem import Problem
    from physmend.tracking import Store


@dataclass
class Outcome:
    """How one trial ended."""

    number: int
    state: str  # COMPLETE | PRUNED | FAIL
    value: float | None = None
    run_id: str | None = None
    reason: str = ""
    restarts: int = 0  # trainings restarted after divergence (sweep.restarts)



@dataclass
class Sweep:
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
    me: dict[str, Any] = field(default_factory=_worker)
    failures_in_a_row: int = 0
    bar: Any = None  # the progress bar of the running loop (messages are written above it)
    target: int | None = None  # trials the study has in the end (sweep.n_trials, or the budget's decision)
    budget_line: str = ""  # the budget's decision, for the summary
    progress: Any = None  # EpochProgress: the bar's "trial 3 epoch 20/120" while a trial trains

    @property
    def n_trials(self) -> int:
        """Trials the study should have in the end: ``sweep.n_trials``, or with ``sweep.budget`` the
        budget's decision once made (until then the minimum, ``sweep.n_trials``)."""
        return self.settings.n_trials if self.target is None else self.target

    def apply_budget(self, bar: Any) -> None:
        """With ``sweep.budget``: once ``sweep.n_trials`` trials reached a verdict, decide how many the
        study has in the end (:mod:`physmend.sweep.budget`), once per study (stored with it; a
        resumed sweep and other workers use the stored decision)."""
        from physmend.sweep.budget import BUDGET_ATTR, wall_span
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
            stored = budget.decision(wall_span(finished), len(finished))
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
            self.fail_stale_trials(bar)
            counts = tally(self.study.get_trials(deepcopy=False))
            self.apply_budget(bar)
            _show(bar, counts)
            if counts.counted + counts.running >= self.n_trials:
                break
            if self.settings.timeout is not None and time.monotonic() - start >= self.settings.timeout:
                _say(bar, f"sweep.timeout of {self.settings.timeout:g} s reached; no new trial is started")
                break
            if self.settings.group > 1:
                batch = self.trial_group(bar, self.group_size(counts))
                if batch is None:
                    break
                for outcome in batch:
                    outcomes.append(outcome)
                    self._after(outcome, bar)
                continue
            outcome = self.one_trial(bar)
            if outcome is None:
                break
            outcomes.append(outcome)
            self._after(outcome, bar)
        return outcomes

    def group_size(self, counts: Tally) -> int:
        """Trials to ask together: ``sweep.group``, but while fewer than ``pruner_startup_trials``
        trials are complete only the missing ones: the median pruner has nothing to compare with
        yet, so a first group would otherwise train every one of its trials to the end."""
        size = min(self.settings.group, self.n_trials - counts.counted - counts.running)
        missing = self.settings.pruner_startup_trials - counts.complete
        if self.settings.pruner == "median" and missing > 0:  # halving compares trials from the first one on
            size = min(size, missing)
        return max(1, size)

    def trial_group(self, bar: Any, size: int) -> list[Outcome] | None:
        """Ask for up to ``size`` trials and train those that can share a solve as one stack
        (:func:`physmend.ude.stacked.train_stack`, grouped by ``stack_key``); each is still its own
        trial with its own child run. ``None`` when no trial could be asked (surplus).

        With ``sweep.group_shapes`` the sampler proposes the first trial's :func:`shape_keys` freely
        and the others' with those values fixed (Optuna's ``PartialFixedSampler``): the group is one
        stack of same-shaped networks (no padding) instead of several stacks solved one after another.
        """
        import optuna
        from optuna.trial import TrialState

        from physmend.ude.stacked import stack_key

        trials: list[Any] = []
        first: dict[int, dict[str, Any]] = {}  # the values of a trial suggested before the others are asked
        shared: dict[str, Any] = {}  # group_shapes: the first trial's shape, which the others take
        for _ in range(max(1, size)):
            sampler = self.settings.sampler_for(len(self.study.get_trials(deepcopy=False)))
            if shared:
                with warnings.catch_warnings():  # PartialFixedSampler is "experimental" since optuna 2.4
                    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                    sampler = optuna.samplers.PartialFixedSampler(shared, sampler)
            self.study.sampler = sampler
            trial = self.study.ask()
            trial.set_user_attr(WORKER_ATTR, self.me)
            if self._surplus(trial):
                trial.set_user_attr(REASON_ATTR, "surplus")
                self.study.tell(trial, state=TrialState.FAIL)
                break
            trials.append(trial)
            if self.settings.group_shapes and not trials[1:]:
                first[trial.number] = self.space.suggest(trial)
                shared = {key: first[trial.number][key] for key in shape_keys(self.space)}
        if not trials:
            return None
        # the others are suggested once the whole group is asked (the order of earlier versions: a
        # study repeated with the same seed proposes the same trials)
        asked = [(trial, first[trial.number] if trial.number in first else self.space.suggest(trial)) for trial in trials]
        outcomes: dict[int, Outcome] = {}
        groups: dict[Any, list[tuple[Any, dict[str, Any], DictConfig, Any]]] = {}
        for trial, values in asked:
            try:
                cfg = self.configs.config(values)
                problem = self.configs.problem(values, cfg)
            except Exception as exc:  # noqa: BLE001 - a bad trial config fails the trial, not the sweep
                outcomes[trial.number] = Outcome(trial.number, "FAIL", reason=f"{type(exc).__name__}: {exc}")
                continue
            groups.setdefault((stack_key(cfg), id(problem)), []).append((trial, values, cfg, problem))
        try:
            with contextlib.ExitStack() as beats:
                for trial, _ in asked:
                    beats.enter_context(Heartbeat(trial, self.settings.heartbeat_interval))
                for members in groups.values():
                    outcomes.update(self._train_group(members))
        except KeyboardInterrupt:
            for trial, _ in asked:
                if trial.number not in outcomes:
                    trial.set_user_attr(REASON_ATTR, "interrupted")
                    self.study.tell(trial, state=TrialState.FAIL)
            raise
        for trial, _ in asked:
            self.tell(trial, outcomes[trial.number])
        return [outcomes[t.number] for t, _ in asked]

    def _train_group(self, members: list[tuple[Any, dict[str, Any], DictConfig, Any]]) -> dict[int, Outcome]:
        """Train one stack; then log each trial's buffered metrics and result to its own child run.
        Trials whose training diverged are trained again together, as a stack of their restarts
        (:mod:`physmend.sweep.restart`), until each finished or has no restart left."""
        import optuna

        from physmend.sweep.restart import Attempts, describe
        from physmend.ude.stacked import train_stack

        reporters = [Reporter(trial, None, self.settings.pruned_because, on_epoch=self.progress) for trial, *_ in members]
        if self.progress is not None:
            self.progress.start([trial.number for trial, *_ in members])
        attempts = [Attempts(cfg, self.settings.restarts) for _, _, cfg, _ in members]
        results: list[Any] = [None] * len(members)
        todo = list(range(len(members)))
        while todo:
            try:
                got: list[Any] = train_stack([attempts[i].current for i in todo], members[0][3],
                                             report=lambda j, epoch, row, todo=todo: reporters[todo[j]](epoch, row),
                                             final_eval="batched", figures=self.settings.figures)
            except Exception as exc:  # noqa: BLE001 - the whole stack failed: each trial's outcome
                if interrupted(exc):  # Ctrl-C inside a library's import or C code
                    raise KeyboardInterrupt from exc
                got = [exc] * len(todo)
            again = []
            for i, result in zip(todo, got):
                if not isinstance(result, BaseException) and not math.isfinite(float(result.val_rmse)):
                    result = FloatingPointError(f"the final val.rmse is not finite ({float(result.val_rmse)})")
                if (isinstance(result, Exception) and not isinstance(result, optuna.TrialPruned)
                        and attempts[i].restart_after(result)):
                    trial = members[i][0]
                    trial.set_user_attr(RESTARTS_ATTR, attempts[i].restarts)
                    reporters[i] = reporters[i].restarted()
                    _say(self.bar, f"trial {trial.number} diverged ({attempts[i].reasons[-1]}); restart "
                                   f"{attempts[i].restarts} of {self.settings.restarts} with {describe(attempts[i].changes)}")
                    again.append(i)
                else:
                    results[i] = attempts[i].final(result) if isinstance(result, Exception) else result
            todo = again
        out: dict[int, Outcome] = {}
        for (trial, values, cfg, _), reporter, result, tried in zip(members, reporters, results, attempts):
            holder: dict[str, str] = {}
            try:
                out[trial.number] = self._log_stacked(trial, values, tried, reporter, result, holder)
            except Exception as exc:  # noqa: BLE001 - diverged, solver failure, anything: FAIL
                self._mark_child(holder.get("run_id"), "FAIL")
                out[trial.number] = Outcome(trial.number, "FAIL", run_id=holder.get("run_id"),
                                            reason=f"{type(exc).__name__}: {exc}", restarts=tried.restarts)
        return out

    def _log_stacked(self, trial: "optuna.Trial", values: dict[str, Any], attempts: Any, reporter: "Reporter",
                     result: Any, holder: dict[str, str]) -> Outcome:
        """``attempts``: the trial's :class:`~physmend.sweep.restart.Attempts` (the child run's config is
        the last attempt's)."""
        import mlflow
        import optuna

        from physmend.sweep.restart import OVERRIDES_TAG, REASONS_TAG, RESTARTS_TAG, describe
        from physmend.tracking import selection as sel

        tags = {"physmend.stacked": "true"}
        if attempts.restarts:
            tags.update({RESTARTS_TAG: str(attempts.restarts), REASONS_TAG: " | ".join(attempts.reasons)[:5000],
                         OVERRIDES_TAG: describe(attempts.changes)})
        with self._child_run(trial, values, attempts.current, holder, tags) as run_:
            for epoch, metrics in reporter.buffered:
                run_.log_metrics(metrics, step=epoch)
            if isinstance(result, optuna.TrialPruned):
                run_.set_tags({sel.TRIAL_STATE_TAG: "PRUNED", "physmend.pruned": str(result) or "pruned"})
                mlflow.end_run("KILLED")
                return Outcome(trial.number, "PRUNED", value=reporter.last_value, run_id=run_.run_id, reason=str(result),
                               restarts=attempts.restarts)
            if isinstance(result, BaseException):
                raise result
            value = float(result.val_rmse)
            if not math.isfinite(value):
                raise FloatingPointError(f"the final val.rmse is not finite ({value})")
            _log_result(run_, result, step=reporter.last_epoch + 1, figures=self.settings.figures)
            run_.set_tags({sel.TRIAL_STATE_TAG: "COMPLETE", RUN_NAME_TAG: trial_name(trial.number, value)})
        return Outcome(trial.number, "COMPLETE", value=value, run_id=run_.run_id, restarts=attempts.restarts)

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
                self._kill_child(holder.get("run_id"), "interrupted (KeyboardInterrupt)")
                raise KeyboardInterrupt from exc
            self._mark_child(holder.get("run_id"), "FAIL")
            return Outcome(trial.number, "FAIL", run_id=holder.get("run_id"), reason=f"{type(exc).__name__}: {exc}")
        except KeyboardInterrupt:
            self._kill_child(holder.get("run_id"), "interrupted (KeyboardInterrupt)")
            raise

    @contextlib.contextmanager
    def _child_run(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, holder: dict[str, str],
                   extra_tags: dict[str, str] | None = None) -> Iterator[Any]:
        """The trial's child run under the sweep's parent, its ID recorded in ``holder`` and the trial."""
        from physmend.tracking import stage_run
        from physmend.tracking import selection as sel

        tags = {sel.STUDY_TAG: self.study.study_name, sel.TRIAL_NUMBER_TAG: str(trial.number), **(extra_tags or {})}
        with stage_run(
            self.store, cfg, stage=sel.TRIAL_STAGE, source_run_id=self.parent_run_id,
            run_name=f"trial-{trial.number:04d}", parent_run_id=self.parent_run_id, tags=tags,
        ) as run_:
            holder["run_id"] = run_.run_id
            trial.set_user_attr(RUN_ID_ATTR, run_.run_id)
            run_.log_params(values)
            yield run_

    def _train_logged(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, problem: "Problem", holder: dict[str, str]) -> Outcome:
        import mlflow
        import optuna

        from physmend.sweep.restart import Attempts
        from physmend.tracking import selection as sel

        with self._child_run(trial, values, cfg, holder) as run_:
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
                    self._record_restart(trial, attempts, run_)
                    reporter = reporter.restarted()
            _log_result(run_, result, step=reporter.last_epoch + 1, figures=self.settings.figures)
            run_.set_tags({sel.TRIAL_STATE_TAG: "COMPLETE", RUN_NAME_TAG: trial_name(trial.number, value)})
        return Outcome(trial.number, "COMPLETE", value=value, run_id=run_.run_id, restarts=attempts.restarts)

    def _record_restart(self, trial: "optuna.Trial", attempts: Any, run_: Any) -> None:
        """A restart of ``trial`` (:class:`physmend.sweep.restart.Attempts`) on its Optuna trial and child
        run (tags, and the ``config.yaml`` later stages load), and one line on the terminal."""
        from physmend.sweep.restart import OVERRIDES_TAG, REASONS_TAG, RESTARTS_ATTR, RESTARTS_TAG, describe

        n = attempts.restarts
        trial.set_user_attr(RESTARTS_ATTR, n)
        run_.set_tags({RESTARTS_TAG: str(n), REASONS_TAG: " | ".join(attempts.reasons)[:5000],
                       OVERRIDES_TAG: describe(attempts.changes)})
        run_.log_text(OmegaConf.to_yaml(attempts.current, resolve=True), "config.yaml")
        _say(self.bar, f"trial {trial.number} diverged ({attempts.reasons[-1]}); restart {n} of "
                       f"{self.settings.restarts} with {describe(attempts.changes)}")

    def _mark_child(self, run_id: str | None, state: str, *, error: str | None = None) -> None:
        from physmend.tracking import ERROR_TAG
        from physmend.tracking import selection as sel

        if run_id is None:
            return
        try:
            self.store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, state)
            if error:
                self.store.client.set_tag(run_id, ERROR_TAG, redact(error))
        except Exception:  # noqa: BLE001 - the trial's FAIL in the study is what counts
            pass

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
            self._kill_child(t.user_attrs.get(RUN_ID_ATTR), f"interrupted: its worker {where} stopped")
            _say(bar, f"trial {t.number} was left running by worker {where}, which stopped; marked FAIL (interrupted)")

    def _kill_child(self, run_id: str | None, reason: str) -> None:
        from physmend.tracking import ERROR_TAG
        from physmend.tracking import selection as sel

        if not run_id:
            return
        try:
            run = self.store.client.get_run(run_id)
            self.store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, "FAIL")
            if run.info.status == "RUNNING" or ERROR_TAG not in run.data.tags:
                self.store.client.set_tag(run_id, ERROR_TAG, redact(reason))
            if run.info.status == "RUNNING":
                self.store.client.set_terminated(run_id, "KILLED")
        except Exception:  # noqa: BLE001 - the run may be gone; the study is the record
            pass
