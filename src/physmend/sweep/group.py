"""Trials asked as a group (``sweep.group`` > 1) and trained as one stack, each still its own trial
with its own child run: :class:`StackedTrials`, part of :class:`physmend.sweep.loop.Sweep`.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig

from physmend.sweep.child import child_run, mark_child
from physmend.sweep.configs import TrialConfigs
from physmend.sweep.outcome import Outcome
from physmend.sweep.report import EpochProgress, Reporter, _log_result, _say
from physmend.sweep.restart import RESTARTS_ATTR, interrupted
from physmend.sweep.settings import Settings, shape_keys
from physmend.sweep.space import SearchSpace
from physmend.sweep.storage import REASON_ATTR, WORKER_ATTR, Tally, asking
from physmend.sweep.workers import Heartbeat
from physmend.tracking.marks import RUN_NAME_TAG, trial_name

if TYPE_CHECKING:
    import optuna
    from physmend.tracking import Store


class StackedTrials:
    """The group methods of :class:`~physmend.sweep.loop.Sweep`: they use the sweep's state below and
    its ``tell`` (record an outcome in the study) and ``_surplus`` (a trial beyond ``n_trials``)."""

    settings: Settings
    space: SearchSpace
    study: Any
    storage: Any
    store: Store
    parent_run_id: str
    configs: TrialConfigs
    me: dict[str, Any]
    bar: Any
    progress: EpochProgress | None
    n_trials: int

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
        (:func:`physmend.ude.stack.train_stack`, grouped by ``stack_key``); each is still its own
        trial with its own child run. ``None`` when no trial could be asked (surplus).

        With ``sweep.group_shapes`` the sampler proposes the first trial's :func:`shape_keys` freely
        and the others' with those values fixed (Optuna's ``PartialFixedSampler``): the group is one
        stack of same-shaped networks (no padding) instead of several stacks solved one after another.
        """
        import optuna
        from optuna.trial import TrialState

        from physmend.ude.stack import stack_key

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
            with asking(self.storage):
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
        from physmend.ude.stack import train_stack

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
                mark_child(self.store, holder.get("run_id"), "FAIL")
                out[trial.number] = Outcome(trial.number, "FAIL", run_id=holder.get("run_id"),
                                            reason=f"{type(exc).__name__}: {exc}", restarts=tried.restarts)
        return out

    def _log_stacked(self, trial: optuna.Trial, values: dict[str, Any], attempts: Any, reporter: Reporter,
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
        with child_run(self.store, self.study.study_name, self.parent_run_id, trial, values, attempts.current, holder,
                       tags) as run_:
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
