"""A trial whose training diverges is restarted (smaller learning rate, shorter segments) before it
counts as failed: the rule (which errors, which settings), the reporter of a restarted attempt
(real Optuna trial), the sweep's divergence line, and a real sweep whose diverging trial is
restarted and ends finished (tiny oscillator trainings, real Optuna and MLflow sqlite stores)."""

from __future__ import annotations

from pathlib import Path

import optuna
import pytest
from omegaconf import OmegaConf

from physmend.config import compose
from physmend.simulate.errors import SimulationError
from physmend.sweep.report import Reporter
from physmend.sweep.restart import RESTARTS_ATTR, Attempts, describe, diverged, one_line, restart_changes
from physmend.sweep.summary import divergence
from physmend.ude import TrainingDiverged, UDEConfigError


def test_only_divergence_restarts_a_trial() -> None:
    assert diverged(TrainingDiverged("loss non-finite")) and diverged(SimulationError("step size underflow"))
    assert diverged(FloatingPointError("the final val.rmse is not finite (nan)"))
    assert not diverged(UDEConfigError("ude.width must be >= 1")) and not diverged(optuna.TrialPruned("pruned"))
    assert not diverged(RuntimeError("DefaultCPUAllocator: can't allocate memory"))


def test_restarts_take_smaller_steps_then_drop_the_warm_start() -> None:
    cfg = compose(["train.lr=0.009", "train.segment_samples=60", "train.warm_start=auto"])
    assert restart_changes(cfg, 1) == {"train.lr": pytest.approx(0.003), "train.segment_samples": 30}
    assert restart_changes(cfg, 2) == {"train.warm_start": "none"}  # another start, the trial's own steps
    assert restart_changes(cfg, 3) == {"train.warm_start": "none", "train.lr": pytest.approx(0.003),
                                       "train.segment_samples": 30}
    cold = compose(["train.lr=0.009", "train.segment_samples=60", "train.warm_start=none"])  # only smaller steps
    assert restart_changes(cold, 2) == {"train.lr": pytest.approx(0.001), "train.segment_samples": 15}
    short = compose(["train.segment_samples=3", "train.warm_start=none"])
    assert restart_changes(short, 1)["train.segment_samples"] == 2  # never below two sampling intervals
    assert restart_changes(short, 2)["train.segment_samples"] == 2
    assert "train.segment_samples" not in restart_changes(compose(["train.segment_samples=2"]), 1)  # at the floor
    seconds = compose(["train.segment_length=5", "train.warm_start=none"])  # a length in the model's time unit: halved
    assert restart_changes(seconds, 2)["train.segment_length"] == pytest.approx(1.25)
    assert describe({"train.lr": 0.0033333, "train.segment_samples": 30}) == "train.lr=0.003333 train.segment_samples=30"
    assert describe({"train.warm_start": "none"}) == "train.warm_start=none"
    with pytest.raises(ValueError, match="restart must be >= 1, but got 0"):
        restart_changes(cfg, 0)


def test_attempts_restart_after_divergence_until_none_is_left() -> None:
    cfg = compose(["train.lr=0.009", "train.segment_samples=60", "train.warm_start=auto"])
    attempts = Attempts(cfg, limit=2)
    assert attempts.current is cfg and attempts.restarts == 0
    assert not attempts.restart_after(UDEConfigError("a wrong setting"))  # not a divergence: fails at once
    assert attempts.restart_after(TrainingDiverged("whole-trajectory\nsimulation failed"))
    assert attempts.reasons == ["TrainingDiverged: whole-trajectory simulation failed"]  # one line
    assert attempts.current.train.lr == pytest.approx(0.003) and attempts.current.train.segment_samples == 30
    assert cfg.train.lr == 0.009  # the trial's own configuration is untouched
    assert attempts.restart_after(SimulationError("step size underflow"))
    current = attempts.current
    assert current.train.warm_start == "none" and current.train.lr == 0.009 and current.train.segment_samples == 60
    last = TrainingDiverged("still diverged")
    assert not attempts.restart_after(last)  # two restarts were all it had
    final = attempts.final(last)
    assert isinstance(final, TrainingDiverged) and final.__cause__ is last
    assert str(final) == ("still diverged (in restart 2 of 2, with train.warm_start=none; the first "
                          "attempt: TrainingDiverged: whole-trajectory simulation failed)")
    assert Attempts(cfg, limit=0).final(last) is last
    assert one_line("a\n  b", limit=3) == "a b" and one_line("abcdef", limit=4) == "abc…"


def test_a_restarted_attempt_logs_after_the_first_and_reports_only_new_epochs_to_optuna() -> None:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(pruner=optuna.pruners.NopPruner())
    trial = study.ask()
    first = Reporter(trial, None, "worse")
    first(0, {"val.rmse": 2.0})
    first(10, {"val.rmse": 1.5, "loss": float("nan")})
    again = first.restarted()
    assert again.step_offset == 11 and again.buffered is first.buffered
    again(0, {"val.rmse": 3.0})
    again(10, {"val.rmse": 1.2})
    again(20, {"val.rmse": 1.0})
    assert [step for step, _ in again.buffered] == [0, 10, 11, 21, 31]  # one MLflow timeline, no step twice
    assert again.last_epoch == 31 and again.last_value == 1.0
    study.tell(trial, 1.0)
    (frozen,) = study.get_trials()
    assert frozen.intermediate_values == {0: 2.0, 10: 1.5, 20: 1.0}  # epochs the first attempt did not reach


def test_the_divergence_line_counts_restarted_and_failed_trials() -> None:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study()
    for restarts, state in ((0, "COMPLETE"), (1, "COMPLETE"), (2, "FAIL"), (0, "FAIL")):
        trial = study.ask()
        if restarts:
            trial.set_user_attr(RESTARTS_ATTR, restarts)
        if state == "COMPLETE":
            study.tell(trial, 1.0)
        else:
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
    line = divergence(study.get_trials(), 2)
    assert line.startswith("divergence: 2 of 4 trials diverged and were restarted (up to 2×: smaller steps, then no "
                           "warm start): 1 then trained to the end or were pruned, 1 failed; 2 of 4 failed in all")
    assert divergence(study.get_trials()[:1], 2) == "divergence: no trial of 1 diverged"


# -- a real sweep ------------------------------------------------------------------------------------
#: tiny trainings of the oscillator (tests/conftest.py) with no warm start: a softplus network at
#: learning rate 3.3333 sends the hybrid 100 ranges past its data within two epochs (every
#: checkpoint fails), at a third of it with segments half as long it trains to the end
DIVERGING = [
    "model=oscillator", "data=oscillator", "train.epochs=2", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "train.warm_start=none", "train.restarts=0", "train.polish=0",
    "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3", "sweep.progress=false", "sweep.figures=false",
]

SPACE = """\
params:
  train.lr: {choice: [3.3333, 0.01]}
  ude.activation: {choice: [softplus]}
  ude.width: {choice: [32]}
first_trials:
  - {train.lr: 3.3333, ude.activation: softplus, ude.width: 32}
  - {train.lr: 0.01, ude.activation: softplus, ude.width: 32}
"""


@pytest.mark.slow
@pytest.mark.usefixtures("reset_mlflow")
@pytest.mark.parametrize("group", [1, 2])
def test_a_diverging_trial_is_restarted_and_ends_finished(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str], group: int) -> None:
    """Alone (group 1: its child run open while it trains) and in a stack with a good trial (group 2:
    the diverged one is trained again as a stack of its own), the trial at lr 3.3333 diverges,
    is restarted once with lr 1.111 and segments of 2.5 s, and completes; its run says so and
    holds the configuration it was trained with (what later stages load)."""
    from physmend.cli import main
    from physmend.tracking import open_store

    monkeypatch.chdir(user_project)
    (user_project / "space.yaml").write_text(SPACE)
    args = ["sweep", "--config-dir", str(user_project / "my_conf"), *DIVERGING, f"sweep.space={user_project / 'space.yaml'}",
            "sweep.n_trials=2", f"sweep.group={group}", "sweep.group_shapes=false", "sweep.study_name=div"]
    assert main(args) == 0
    out = capsys.readouterr()
    study = optuna.load_study(study_name="div", storage=f"sqlite:///{user_project / 'optuna.db'}")
    assert [t.state.name for t in study.trials] == ["COMPLETE", "COMPLETE"]
    assert study.trials[0].user_attrs[RESTARTS_ATTR] == 1 and RESTARTS_ATTR not in study.trials[1].user_attrs
    (line,) = [l for l in out.err.splitlines() if l.startswith("trial 0 diverged (")]
    assert line.startswith("trial 0 diverged (TrainingDiverged: whole-trajectory simulation of the hybrid failed")
    assert line.endswith("restart 1 of 2 with train.lr=1.111 train.segment_length=2.5")
    assert ("divergence: 1 of 2 trials diverged and were restarted (up to 2×: smaller steps, then no warm start): "
            "1 then trained to the end or were pruned, 0 failed; 0 of 2 failed in all") in out.out
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{user_project / 'mlflow.db'}", "experiment": "physmend"}))
    run = store.client.get_run(study.trials[0].user_attrs["mlflow_run_id"])
    assert run.data.tags["physmend.restarts"] == "1" and run.data.tags["physmend.trial_state"] == "COMPLETE"
    assert run.data.tags["physmend.restart.overrides"] == "train.lr=1.111 train.segment_length=2.5"
    assert run.data.params["train.lr"] == "3.3333"  # what the sampler proposed
    stored = OmegaConf.load(store.client.download_artifacts(run.info.run_id, "config.yaml", str(user_project)))
    assert stored.train.lr == pytest.approx(3.3333 / 3) and stored.train.segment_length == pytest.approx(2.5)
    steps = [m.step for m in store.client.get_metric_history(run.info.run_id, "val.rmse")]
    assert steps == sorted(steps) and len(steps) == len(set(steps))  # one timeline: the restart after the first


def test_a_mask_candidate_without_a_validation_rmse_says_why_in_its_line() -> None:
    from physmend.masking.choice import val_text

    reason = TrainingDiverged("whole-trajectory simulation of the hybrid failed:\n the hybrid diverged in 'h2'")
    assert val_text(reason) == ("nan (TrainingDiverged: whole-trajectory simulation of the hybrid failed: the hybrid "
                                 "diverged in 'h2')")


def test_a_ctrl_c_inside_an_extension_import_is_an_interruption_not_a_failure() -> None:
    from physmend.sweep.restart import interrupted

    # what a compiled extension raises when Ctrl-C lands during its initialisation (pybind11: an
    # ImportError "initialization failed" raised from the KeyboardInterrupt), then wrapped once more
    try:
        try:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as stop:
                raise ImportError("initialization failed") from stop
        except ImportError:
            raise RuntimeError("trial failed") from None
    except RuntimeError as wrapped:
        assert interrupted(wrapped)
    assert not interrupted(ImportError("initialization failed"))
    assert not interrupted(ValueError("lr must be > 0"))
