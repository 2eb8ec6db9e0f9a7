"""``sweep.budget``: a sweep sized by what its trials cost. The rule's arithmetic, its wall-time
measure on real Optuna trials, and real sweeps (tiny oscillator trainings, real Optuna and MLflow
sqlite stores in a temporary folder) that run more than the minimum where the budget allows, never
more than ``sweep.max_trials``, and keep the decision when resumed."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import optuna
import pytest

from physmend.cli import main
from physmend.config import ConfigError, compose
import physmend.sweep as sw
from physmend.sweep.budget import BUDGET_ATTR, Budget, at_once, wall_span

TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=2", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "train.polish=0", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.progress=false", "sweep.space=small", "sweep.figures=false",
]

pytestmark = pytest.mark.usefixtures("reset_mlflow")  # tests/conftest.py


def test_as_many_trials_as_fit_within_the_bounds() -> None:
    budget = Budget(60.0, 2, 16)
    assert budget.trials(30.0, 2) == 4  # 15 s each, 30 s left: two more
    assert budget.trials(31.0, 2) == 3  # 15.5 s each, 29 s left: one more
    assert budget.trials(80.0, 2) == 2  # the minimum took longer than the budget: no more
    assert budget.trials(4.0, 2) == 16  # 2 s each: 30 fit, at most 16
    assert budget.trials(0.0, 2) == 16  # too fast to measure: the most
    assert budget.trials(5.0, 0) == 2
    stored = budget.decision(30.0, 2)
    assert stored == {"budget": 60.0, "min": 2, "max": 16, "trials": 4, "spent": 30.0, "measured": 2, "at_once": 1}
    assert budget.matches(stored) and not Budget(61.0, 2, 16).matches(stored) and not budget.matches(None)
    line = budget.describe(stored)
    assert "budget 60 s: the first 2 trials took 30.0 s (15.0 s each), so 4 trials in all" in line
    assert "sweep.n_trials=4 sweep.budget=null" in line


def test_trials_that_ran_side_by_side_come_in_rounds() -> None:
    """Two at a time (two workers, or a stack of two): one more trial costs a whole round."""
    budget = Budget(60.0, 2, 16)
    assert budget.trials(40.0, 2, at_once=2) == 2  # a round took 40 s, 20 s left: no round fits (one at a time: 3)
    assert budget.trials(40.0, 2) == 3
    assert budget.trials(20.0, 2, at_once=2) == 6  # 20 s a round, 40 s left: two rounds of two
    assert budget.trials(25.0, 2, at_once=2) == 4  # 35 s left: one round
    assert budget.trials(10.0, 4, at_once=2) == 16  # 5 s a round: many; at most 16
    assert budget.trials(40.0, 2, at_once=5) == budget.trials(40.0, 2, at_once=2)  # never more at once than measured
    stored = budget.decision(40.0, 2, at_once=2)
    assert stored["trials"] == 2 and stored["at_once"] == 2 and budget.matches(stored)
    assert "took 40.0 s (20.0 s each, 2 at a time), so 2 trials in all (the budget allows no more" in budget.describe(stored)
    assert "at a time" not in budget.describe(budget.decision(40.0, 2))


@pytest.mark.parametrize(("args", "message"), [
    ((0.0, 1, 2), "a budget must be a finite number of seconds > 0, but got 0.0"),
    ((float("inf"), 1, 2), "a budget must be a finite number of seconds > 0, but got inf"),
    ((10.0, 3, 2), "`1 <= min_trials <= max_trials` must hold, but got (min_trials=3, max_trials=2)"),
])
def test_a_bad_budget_states_the_rule_and_the_value(args: tuple[float, int, int], message: str) -> None:
    with pytest.raises(ValueError) as err:
        Budget(*args)
    assert str(err.value) == message


def test_settings_budget_and_its_bounds() -> None:
    assert sw.Settings.from_cfg(compose([]).sweep).budgeted is None  # `physmend sweep`: a count, as before
    settings = sw.Settings.from_cfg(compose(["sweep.budget=30", "sweep.n_trials=2", "sweep.max_trials=8"]).sweep)
    assert settings.budgeted == Budget(30.0, 2, 8)
    low = sw.Settings.from_cfg(compose(["sweep.budget=30", "sweep.n_trials=5", "sweep.max_trials=3"]).sweep)
    assert low.budgeted == Budget(30.0, 5, 5)  # max below the minimum: the minimum
    with pytest.raises(ConfigError, match=r"sweep.budget must be a number > 0, but got -1"):
        sw.Settings.from_cfg(compose(["sweep.budget=-1"]).sweep)
    with pytest.raises(ConfigError, match=r"sweep.budget must be a number > 0, but got 0"):
        sw.Settings.from_cfg(compose(["sweep.budget=0"]).sweep)
    discover = compose([]).discover
    assert discover.budget > 0 and discover.max_trials >= discover.n_trials  # discover searches by cost


def test_wall_span_is_first_start_to_last_end_of_real_trials() -> None:
    t0 = dt.datetime(2026, 1, 1, 12, 0, 0)

    def frozen(number: int, start: float, end: float) -> optuna.trial.FrozenTrial:
        return optuna.trial.FrozenTrial(
            number=number, state=optuna.trial.TrialState.COMPLETE, value=1.0, values=None,
            datetime_start=t0 + dt.timedelta(seconds=start), datetime_complete=t0 + dt.timedelta(seconds=end),
            params={}, distributions={}, user_attrs={}, system_attrs={}, intermediate_values={}, trial_id=number,
        )

    # two trials trained together as one stack overlap: they cost what the stack took, not twice that
    assert wall_span([frozen(0, 0.0, 40.0), frozen(1, 0.5, 41.0)]) == pytest.approx(41.0)
    assert wall_span([frozen(0, 0.0, 10.0), frozen(1, 10.0, 25.0)]) == pytest.approx(25.0)
    assert wall_span([]) == 0.0
    # how many ran at once: summed durations over the span, to the nearest whole number
    assert at_once([frozen(0, 0.0, 40.0), frozen(1, 0.5, 41.0)]) == 2
    assert at_once([frozen(0, 0.0, 36.0), frozen(1, 7.0, 45.0)]) == 2  # a worker that started later
    assert at_once([frozen(0, 0.0, 10.0), frozen(1, 10.0, 25.0)]) == 1
    assert at_once([frozen(0, 0.0, 10.0), frozen(1, 1.0, 11.0), frozen(2, 11.0, 21.0), frozen(3, 11.5, 21.5)]) == 2
    assert at_once([]) == 1


def _sweep(project: Path, *extra: str) -> int:
    return main(["sweep", "--config-dir", str(project / "my_conf"), *TINY, *extra])


def _study(project: Path, name: str) -> optuna.Study:
    return optuna.load_study(study_name=name, storage=f"sqlite:///{project / 'optuna.db'}")


@pytest.mark.slow
def test_a_cheap_problem_runs_more_trials_within_the_budget_never_more_than_max(
        user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Tiny trainings against a budget far above what they take: the sweep goes past its minimum (1)
    and stops at sweep.max_trials (3); resumed, it keeps the stored decision and runs nothing more."""
    monkeypatch.chdir(user_project)
    assert _sweep(user_project, "sweep.n_trials=1", "sweep.max_trials=3", "sweep.budget=100000",
                  "sweep.study_name=cheap") == 0
    out = capsys.readouterr()
    study = _study(user_project, "cheap")
    assert len(study.trials) == 3
    stored = study.user_attrs[BUDGET_ATTR]
    assert stored["trials"] == 3 and stored["measured"] == 1 and stored["min"] == 1 and stored["max"] == 3
    assert "3 of 3 trials" in out.out and "so 3 trials in all (the most allowed (sweep.max_trials)" in out.out
    assert "divergence: no trial of 3 diverged" in out.out
    assert _sweep(user_project, "sweep.n_trials=1", "sweep.max_trials=3", "sweep.budget=100000",
                  "sweep.study_name=cheap") == 0
    assert len(_study(user_project, "cheap").trials) == 3  # the decision is the study's: nothing more to run
    # a budget smaller than the minimum's cost: the minimum only
    assert _sweep(user_project, "sweep.n_trials=1", "sweep.max_trials=3", "sweep.budget=0.001",
                  "sweep.study_name=dear") == 0
    assert len(_study(user_project, "dear").trials) == 1
    assert "so 1 trial in all (the budget allows no more" in capsys.readouterr().out
