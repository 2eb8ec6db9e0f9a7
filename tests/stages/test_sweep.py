"""physmend sweep: own Optuna loop, MLflow parent/child runs, resume, workers, failures, pruning.

Real MLflow and Optuna sqlite stores in a temporary folder; real (tiny) training on the user's
oscillator model from conftest.py.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest
from omegaconf import OmegaConf

from physmend.cli import main
from physmend.config import ConfigError, compose
import physmend.sweep as sw
from physmend.stages import sweep as stage

TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=4", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.progress=false",
]
STUDY = "oscillator-oscillator-small"


pytestmark = pytest.mark.usefixtures("reset_mlflow")  # tests/conftest.py


def sweep_args(project: Path, *extra: str) -> list[str]:
    return ["sweep", "--config-dir", str(project / "my_conf"), *TINY, *extra]


def open_stores(project: Path) -> tuple[Any, Any]:
    """The MLflow store and the Optuna storage URL of ``project``."""
    from physmend.tracking import open_store

    store = open_store(OmegaConf.create({"uri": f"sqlite:///{project / 'mlflow.db'}", "experiment": "physmend"}))
    return store, f"sqlite:///{project / 'optuna.db'}"


def load_study(project: Path, name: str = STUDY) -> Any:
    import optuna

    return optuna.load_study(study_name=name, storage=f"sqlite:///{project / 'optuna.db'}")


def children(store: Any, parent: str) -> list[Any]:
    runs = store.client.search_runs([store.experiment_id], f"tags.`mlflow.parentRunId` = '{parent}'")
    return sorted(runs, key=lambda r: int(r.data.tags["physmend.trial_number"]))


def sweep_parents(store: Any) -> list[Any]:
    return store.client.search_runs([store.experiment_id], "tags.`physmend.stage` = 'sweep'")


def write_space(project: Path, text: str, name: str = "space.yaml") -> Path:
    path = project / name
    path.write_text(textwrap.dedent(text))
    return path


# -- search spaces -----------------------------------------------------------------------------
def test_every_shipped_space_loads_and_every_choice_composes() -> None:
    names = sw.available_spaces()
    assert {"default", "small"} <= set(names)
    for name in names:
        space = sw.load_space(name)
        assert space.description and space.params
        for key, param in space.params.items():
            for value in param.examples():
                cfg = compose(sw.trial_overrides({key: value}))
                assert OmegaConf.select(cfg, key) == value, (name, key, value)
        for first in space.first_trials:
            cfg = compose(sw.trial_overrides(first))
            assert all(OmegaConf.select(cfg, k) == v for k, v in first.items())


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"train.lr": {"log_uniform": [0.1, 0.01]}}, "params.train.lr.log_uniform needs 0 < low <= high, but got [0.1, 0.01]"),
        ({"train.lr": {"log_uniform": [0.0, 0.01]}}, "params.train.lr.log_uniform needs 0 < low <= high, but got [0.0, 0.01]"),
        ({"train.lr": {"uniform": [3, 1]}}, "params.train.lr.uniform needs low <= high, but got [3, 1]"),
        ({"ude.width": {"int": [4.5, 8]}}, "params.ude.width.int needs integers low <= high, but got [4.5, 8]"),
        ({"ude.width": {"int": [4, 8], "step": 0}}, "params.ude.width.int: step must be an integer >= 1, but got 0"),
        ({"ude.width": {"choice": []}}, "params.ude.width.choice needs a non-empty list of values, but got []"),
        ({"ude.width": {"choice": [4, 4]}}, "params.ude.width.choice values must be distinct, but [4] repeat"),
        ({"ude.width": {"choice": [[4, 4]]}}, "values must be numbers, strings, booleans or null, but got [4, 4]"),
        ({"ude.width": {"normal": [1, 2]}}, "params.ude.width needs exactly one of choice, uniform, log_uniform, int, but got keys ['normal']"),
        ({"ude.width": {"choice": [4], "step": 2}}, "params.ude.width: unknown keys ['step'] for choice"),
        ({"ude.width": 4}, "params.ude.width must be a mapping like {choice: [...]}, but got 4"),
        ({"+ude.width": {"choice": [4]}}, "a parameter must be a config key like 'train.lr', but got '+ude.width'"),
    ],
)
def test_bad_search_spaces_name_file_and_key(params: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as err:
        sw.parse_space({"params": params}, name="mine", label="sweeps/mine.yaml")
    assert str(err.value).startswith("sweeps/mine.yaml: ")
    assert message in str(err.value)


def test_shape_keys_and_the_group_shapes_flag() -> None:
    """The keys a group's trials share: those that shape the stacked solve, and width and depth."""
    assert sw.shape_keys(sw.load_space("default")) == ["ude.width", "ude.depth", "train.segment_samples"]
    space = sw.parse_space({"params": {"simulate.rtol": {"choice": [1e-4, 1e-5]}, "train.lr": {"choice": [0.1]},
                                       "ude.activation": {"choice": ["tanh"]}}}, name="s", label="s.yaml")
    assert sw.shape_keys(space) == ["simulate.rtol"]
    assert sw.Settings.from_cfg(compose([]).sweep).group_shapes is True
    assert sw.Settings.from_cfg(compose(["sweep.group_shapes=false"]).sweep).group_shapes is False
    with pytest.raises(ConfigError, match="sweep.group_shapes must be true or false, but got 'no'"):
        sw.Settings.from_cfg(compose(["sweep.group_shapes=no"]).sweep)


def test_bad_space_files_and_first_trials(tmp_path: Path) -> None:
    path = write_space(tmp_path, "params:\n  ude.width: {choice: [4, 8]}\nfirst_trials:\n  - {ude.width: 16}\n")
    with pytest.raises(ConfigError, match=r"first_trials\[0\]: ude.width=16 lies outside params.ude.width"):
        sw.load_space(str(path))
    path.write_text("params: [1, 2\n")
    with pytest.raises(ConfigError, match="space.yaml: not a valid YAML file"):
        sw.load_space(str(path))
    with pytest.raises(ConfigError, match=r"must name a search space shipped with physmend \(default, small"):
        sw.load_space("no_such_space")
    assert sw.hydra_value("tanh") == "tanh" and sw.hydra_value("null") == "'null'" and sw.hydra_value(1e-6) == "1e-06"


def test_a_bad_space_or_key_is_an_error_before_anything_is_written(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    bad = write_space(user_project, "params:\n  train.lr: {log_uniform: [0.1, 0.01]}\n")
    assert main(sweep_args(user_project, f"sweep.space={bad}")) == 2
    err = capsys.readouterr().err
    assert f"{bad}: params.train.lr.log_uniform needs 0 < low <= high, but got [0.1, 0.01]" in err
    typo = write_space(user_project, "params:\n  ude.widht: {choice: [4, 8]}\n", "typo.yaml")
    assert main(sweep_args(user_project, f"sweep.space={typo}")) == 2
    err = capsys.readouterr().err
    assert "params.ude.widht = 4 does not compose" in err and "ude.widht" in err
    assert main(sweep_args(user_project, "sweep.space=small", "ude.width=4")) == 2
    assert "ude.width: set on the command line and searched by sweeps/small.yaml" in capsys.readouterr().err
    assert main(sweep_args(user_project, "sweep.sampler=grid")) == 2
    assert "sweep.sampler must be one of ['tpe', 'random'], but got 'grid'" in capsys.readouterr().err
    assert not (user_project / "mlflow.db").exists() and not (user_project / "optuna.db").exists()


# -- a sweep, resumed ----------------------------------------------------------------------------
def test_sweep_resume_structure_selection_and_reload(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    from physmend.tracking import current_selection, load_trial
    from physmend.ude import evaluate
    from physmend.ude.metrics import checkpoint_problem

    monkeypatch.chdir(user_project)
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=2")) == 0
    first_out = capsys.readouterr().out
    store, _ = open_stores(user_project)
    (parent,) = sweep_parents(store)
    parent_id = parent.info.run_id
    assert parent_id in first_out and "physmend select RUN_ID" in first_out and "physmend runs" in first_out

    # same command, more trials: same study, same parent, only the missing trial runs
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=3")) == 0
    out = capsys.readouterr().out
    study = load_study(user_project)
    trials = study.get_trials()
    assert [t.number for t in trials] == [0, 1, 2]
    assert all(t.state.name == "COMPLETE" for t in trials)
    assert [p.info.run_id for p in sweep_parents(store)] == [parent_id]
    assert study.user_attrs[sw.PARENT_ATTR] == parent_id
    kids = children(store, parent_id)
    assert [k.info.run_name.lstrip("★ ")[:10] for k in kids] == ["trial-0000", "trial-0001", "trial-0002"]
    assert [t.user_attrs[sw.RUN_ID_ATTR] for t in trials] == [k.info.run_id for k in kids]

    # tags and contents of parent and children
    parent = store.client.get_run(parent_id)
    tags = parent.data.tags
    assert parent.info.status == "FINISHED"
    assert tags["physmend.stage"] == "sweep" and tags["physmend.study"] == STUDY and tags["physmend.space"] == "small"
    assert tags["physmend.source_run_id"] == "" and tags["physmend.data"] == "oscillator"
    assert parent.data.metrics["trials.complete"] == 3
    for trial, kid in zip(trials, kids):
        kt = kid.data.tags
        assert kid.info.status == "FINISHED"
        assert kt["physmend.stage"] == "trial" and kt["physmend.study"] == STUDY
        assert kt["physmend.trial_number"] == str(trial.number) and kt["mlflow.parentRunId"] == parent_id
        assert kt["physmend.trial_state"] == "COMPLETE"
        assert kid.data.params == {k: str(v) for k, v in trial.params.items()}
        assert kid.data.metrics["val.rmse"] == pytest.approx(trial.value, rel=1e-12)
        history = store.client.get_metric_history(kid.info.run_id, "val.rmse")
        assert [m.step for m in history] == [0, 2, 4, 6, 7]  # warm start, per epoch, the polish (train.polish), then the final (best) value
        files = {f.path for f in store.client.list_artifacts(kid.info.run_id)}
        assert {"config.yaml", "model", "plots", "history.json"} <= files
        assert {f.path for f in store.client.list_artifacts(kid.info.run_id, "model")} == {"model/hybrid.json", "model/weights.pt"}
        cfg = OmegaConf.load(store.client.download_artifacts(kid.info.run_id, "config.yaml", str(user_project)))
        assert all(OmegaConf.select(cfg, k) == v for k, v in trial.params.items())  # a real composed trial config
        assert cfg.train.epochs == 4

    # the selection is the best trial by val.rmse
    best = min(trials, key=lambda t: t.value)
    best_run = best.user_attrs[sw.RUN_ID_ATTR]
    assert tags["physmend.best_run_id"] == best_run == tags["physmend.selected_run_id"]
    assert tags["physmend.selected_by"] == "auto" and tags["physmend.selected_at"].endswith("+00:00")
    # in the MLflow UI: the best trial carries a tag, the sweep run's description names it, the
    # experiment is a classic ML one (its runs table, not the GenAI view)
    marks = {k.info.run_id: store.client.get_run(k.info.run_id).data.tags.get("physmend.best") for k in kids}
    assert marks[best_run] == "true" and all(v != "true" for r, v in marks.items() if r != best_run), marks
    assert best_run in tags["mlflow.note.content"] and "val.rmse" in tags["mlflow.note.content"]
    assert store.client.get_experiment(store.experiment_id).tags["mlflow.experimentKind"] == "custom_model_development"
    assert current_selection(store) == best_run
    assert f"best: trial {best.number}" in out and best_run in out

    # reload from the run ID reproduces the logged metric (a trial is judged without the test
    # experiments: the same problem, the same solve)
    loaded = load_trial(store, kids[1].info.run_id)
    assert loaded.cfg.ude.width == trials[1].params["ude.width"]
    assert any(e.role == "test" for e in loaded.problem.experiments)
    assert evaluate(loaded.hybrid, checkpoint_problem(loaded.problem), loaded.cfg)["val.rmse"] == pytest.approx(
        kids[1].data.metrics["val.rmse"], rel=1e-6)
    cfg, _, hybrid = load_trial(store)  # None: the current selection
    assert cfg.ude.width == best.params["ude.width"]
    assert hybrid is not None

    # a third run of the same command has nothing left to do
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=3")) == 0
    assert len(load_study(user_project).get_trials()) == 3 and len(children(store, parent_id)) == 3
    # resuming with another training configuration would mix incomparable trials
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=4", "train.epochs=8")) == 2
    assert "train.epochs: 4 -> 8" in capsys.readouterr().err
    assert len(load_study(user_project).get_trials()) == 3


# -- failures and pruning ------------------------------------------------------------------------
FAIL_PRUNE_SPACE = """\
description: one good trial, one that diverges, one that is pruned
params:
  ude.output_scale: {choice: [0.1, 1.0e+300]}
  train.lr: {choice: [0.01, 1.0e-7]}
  ude.width: {choice: [4]}
first_trials:
  - {ude.output_scale: 0.1, train.lr: 0.01}
  - {ude.output_scale: 1.0e+300, train.lr: 0.01}
  - {ude.output_scale: 0.1, train.lr: 1.0e-7}
"""


@pytest.mark.parametrize("pruner", [["sweep.pruner=median"], ["sweep.pruner=halving", "sweep.pruner_min_epochs=2"]])
def test_diverging_trial_fails_pruned_trial_stops_sweep_goes_on(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys,  # noqa: ANN001
                                                               pruner: list[str]) -> None:
    """The trial that learns nothing (lr 1e-7) is worse than the first at epoch 2: the median
    pruner stops it there, and so does successive halving (rung 2: only the best third goes on)."""
    monkeypatch.chdir(user_project)
    space = write_space(user_project, FAIL_PRUNE_SPACE)
    args = sweep_args(user_project, f"sweep.space={space}", "sweep.n_trials=3", "sweep.pruner_startup_trials=1",
                      "sweep.study_name=fp", *pruner)
    assert main(args) == 0
    captured = capsys.readouterr()
    study = load_study(user_project, "fp")
    states = [t.state.name for t in study.get_trials()]
    assert states == ["COMPLETE", "FAIL", "PRUNED"]
    failed = study.trials[1]
    reason = failed.user_attrs["fail_reason"]  # the huge correction fails the warm start's evaluation or the loss
    assert reason.startswith("TrainingDiverged: ") and ("non-finite" in reason or "simulation of the hybrid failed" in reason)
    assert "trial 1 failed: TrainingDiverged" in captured.err
    store, _ = open_stores(user_project)
    ok, bad, pruned = children(store, study.user_attrs[sw.PARENT_ATTR])
    assert bad.info.status == "FAILED" and bad.data.tags["physmend.trial_state"] == "FAIL"
    assert bad.data.tags["physmend.error"] == reason
    assert pruned.info.status == "KILLED" and pruned.data.tags["physmend.trial_state"] == "PRUNED"
    because = "best third" if "sweep.pruner=halving" in pruner else "median"  # the message names the pruner's rule
    assert pruned.data.tags["physmend.pruned"].startswith("pruned at epoch 2: val.rmse ") and because in pruned.data.tags["physmend.pruned"]
    assert [m.step for m in store.client.get_metric_history(pruned.info.run_id, "val.rmse")] == [0, 2]
    assert study.trials[2].intermediate_values and study.trials[2].intermediate_values[2] > study.trials[0].intermediate_values[2]
    parent = store.client.get_run(study.user_attrs[sw.PARENT_ATTR])
    assert parent.data.tags["physmend.selected_run_id"] == ok.info.run_id == study.trials[0].user_attrs[sw.RUN_ID_ATTR]
    assert parent.info.status == "FINISHED"


def test_consecutive_failures_stop_the_sweep(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    space = write_space(user_project, "params:\n  ude.output_scale: {choice: [1.0e+300, 1.0e+299]}\n")
    args = sweep_args(user_project, f"sweep.space={space}", "sweep.n_trials=5", "sweep.max_failures_in_a_row=2")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "2 trials in a row failed (sweep.max_failures_in_a_row = 2)" in err
    store, _ = open_stores(user_project)
    (parent,) = sweep_parents(store)
    assert parent.info.status == "FAILED" and "physmend.selected_run_id" not in parent.data.tags


def test_a_sweep_where_no_trial_finishes_exits_non_zero(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                       capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    space = write_space(user_project, "params:\n  ude.output_scale: {choice: [1.0e+300]}\n")
    args = sweep_args(user_project, f"sweep.space={space}", "sweep.n_trials=1", "sweep.max_failures_in_a_row=5")
    assert main(args) == 2
    captured = capsys.readouterr()
    assert "no trial finished training, so nothing is selected" in captured.out  # the summary still says what happened
    (line,) = [l for l in captured.err.splitlines() if "error:" in l]
    assert "none of its 1 trials finished training (1 failed, 0 pruned)" in line
    store, _ = open_stores(user_project)
    (parent,) = sweep_parents(store)
    assert parent.info.status == "FINISHED" and "physmend.selected_run_id" not in parent.data.tags


# -- interrupted and stale trials ------------------------------------------------------------------
def _wait_for(predicate: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def _running_with_run(project: Path, name: str = STUDY) -> bool:
    if not (project / "optuna.db").exists():
        return False
    try:
        trials = load_study(project, name).get_trials()
    except Exception:  # noqa: BLE001 - not created yet
        return False
    return any(t.state.name == "RUNNING" and sw.RUN_ID_ATTR in t.user_attrs for t in trials)


SLOW_FIRST_SPACE = """\
params:
  train.epochs: {choice: [400, 4]}
  ude.width: {choice: [4, 5]}
first_trials:
  - {train.epochs: 400, ude.width: 4}
  - {train.epochs: 4, ude.width: 4}
  - {train.epochs: 4, ude.width: 5}
"""


def _as_from_a_shell() -> None:
    """In the child before exec: SIGINT unblocked and at its default, as a shell starts a command
    (the test process may have inherited or set another disposition)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_fails_the_trial_and_a_rerun_replaces_it(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    space = write_space(user_project, SLOW_FIRST_SPACE)
    # the first trial must still be running when the signal comes: no early stopping
    args = [a for a in sweep_args(user_project, f"sweep.space={space}", "sweep.n_trials=2", "sweep.study_name=slow")
            if a != "train.epochs=4"] + ["train.patience=0"]
    proc = subprocess.Popen([sys.executable, "-m", "physmend.cli", *args], cwd=user_project,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_as_from_a_shell)
    try:
        _wait_for(lambda: proc.poll() is not None or _running_with_run(user_project, "slow"), 120, "a running trial")
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=180)  # generous: a loaded machine handles the signal late
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "physmend sweep: interrupted" in err
    study = load_study(user_project, "slow")
    t0 = study.trials[0]
    assert t0.state.name == "FAIL" and t0.user_attrs["fail_reason"] == "interrupted"
    assert [t.state.name for t in study.trials[1:]] == ["WAITING", "WAITING"]
    store, _ = open_stores(user_project)
    parent_id = study.user_attrs[sw.PARENT_ATTR]
    kid = store.client.get_run(t0.user_attrs[sw.RUN_ID_ATTR])
    assert kid.info.status == "KILLED" and kid.data.tags["physmend.trial_state"] == "FAIL"
    assert "KeyboardInterrupt" in kid.data.tags["physmend.error"] or "interrupted" in kid.data.tags["physmend.error"]
    assert store.client.get_run(parent_id).info.status == "KILLED"

    # the same command resumes: the interrupted trial reached no verdict, so two trials still run
    assert main(args) == 0
    trials = load_study(user_project, "slow").get_trials()
    assert [t.state.name for t in trials] == ["FAIL", "COMPLETE", "COMPLETE"]
    assert [p.info.run_id for p in sweep_parents(store)] == [parent_id]
    assert store.client.get_run(parent_id).info.status == "FINISHED"
    assert len(children(store, parent_id)) == 3
    capsys.readouterr()


def test_stale_trial_of_a_dead_worker_is_failed_and_replaced(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    from optuna.trial import TrialState

    monkeypatch.chdir(user_project)
    # from Python, without the overrides: trial values are patched into the composed config
    cfg = compose(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=1")[3:], user_config_dir=user_project / "my_conf")
    parent_id = stage.run(cfg)
    store, _ = open_stores(user_project)
    (kid,) = children(store, parent_id)
    trial_cfg = OmegaConf.load(store.client.download_artifacts(kid.info.run_id, "config.yaml", str(user_project)))
    assert trial_cfg.ude.width == int(kid.data.params["ude.width"]) and trial_cfg.train.epochs == 4
    # a worker that died mid-trial leaves a RUNNING trial behind: same host, a PID that no longer exists
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    study = load_study(user_project)
    orphan = study.ask()
    orphan.set_user_attr(sw.WORKER_ATTR, {"host": sw.this_worker()["host"], "pid": dead.pid})
    orphan.set_user_attr(sw.HEARTBEAT_ATTR, time.time())
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=2")) == 0  # the CLI resumes it
    err = capsys.readouterr().err
    assert f"trial {orphan.number} was left running by worker" in err and "marked FAIL (interrupted)" in err
    trials = load_study(user_project).get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL, TrialState.COMPLETE]
    assert trials[1].user_attrs["fail_reason"] == "interrupted"
    assert sw.tally(trials).counted == 2


def test_is_stale_by_pid_and_by_heartbeat() -> None:
    import datetime as dt

    from optuna.trial import TrialState, create_trial

    me = {"host": "here", "pid": os.getpid()}
    now = time.time()

    def running(attrs: dict[str, Any]) -> Any:
        t = create_trial(state=TrialState.RUNNING, user_attrs=attrs)
        t.datetime_start = dt.datetime.now()
        return t

    alive = os.getppid()
    assert not sw.is_stale(running({"worker": {"host": "here", "pid": alive}, "heartbeat": now}), now=now, stale_after=60, me=me)
    assert sw.is_stale(running({"worker": {"host": "here", "pid": me["pid"]}, "heartbeat": now}), now=now, stale_after=60, me=me)
    assert not sw.is_stale(running({"worker": {"host": "there", "pid": 1}, "heartbeat": now - 30}), now=now, stale_after=60, me=me)
    assert sw.is_stale(running({"worker": {"host": "there", "pid": 1}, "heartbeat": now - 90}), now=now, stale_after=60, me=me)
    assert not sw.is_stale(running({}), now=now, stale_after=60, me=me)  # just asked: no worker recorded yet
    # workers in two containers with equal host names and PIDs: told apart by their random IDs and
    # namespaces, so a live one (fresh heartbeat) is never marked stale by the other
    mine = {"id": "f" * 32, "host": "box", "pid": os.getpid(), "ns": "boot-a:4026531836"}
    twin = {"id": "0" * 32, "host": "box", "pid": os.getpid(), "ns": "boot-b:4026531836"}
    assert not sw.is_stale(running({"worker": twin, "heartbeat": now - 30}), now=now, stale_after=60, me=mine)
    assert sw.is_stale(running({"worker": twin, "heartbeat": now - 90}), now=now, stale_after=60, me=mine)
    assert sw.is_stale(running({"worker": dict(mine), "heartbeat": now}), now=now, stale_after=60, me=mine)
    gone = {**twin, "ns": mine["ns"], "pid": 2 ** 22 + 17}  # same namespace, a PID that does not exist
    assert sw.is_stale(running({"worker": gone, "heartbeat": now}), now=now, stale_after=60, me=mine)


# -- several workers -------------------------------------------------------------------------------
def test_two_worker_processes_share_one_study(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cmd = [sys.executable, "-m", "physmend.cli", *sweep_args(user_project, "sweep.space=small", "sweep.n_trials=4", "sweep.pruner=none")]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    procs = [subprocess.Popen(cmd, cwd=user_project, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, results):
        assert p.returncode == 0, err
    study = load_study(user_project)
    trials = study.get_trials()
    counted = [t for t in trials if t.state.is_finished() and t.user_attrs.get("fail_reason") != "surplus"]
    assert len(counted) == 4 and all(t.state.name == "COMPLETE" for t in counted)
    workers = {t.user_attrs[sw.WORKER_ATTR]["pid"] for t in counted}
    assert workers == {p.pid for p in procs}  # both did work
    store, _ = open_stores(user_project)
    (parent,) = sweep_parents(store)
    kids = children(store, parent.info.run_id)
    assert sorted(k.info.run_id for k in kids) == sorted(t.user_attrs[sw.RUN_ID_ATTR] for t in counted)
    assert parent.info.status == "FINISHED"
    best = min(counted, key=lambda t: t.value)
    assert parent.data.tags["physmend.selected_run_id"] == best.user_attrs[sw.RUN_ID_ATTR]
    assert math.isfinite(parent.data.metrics["best.val.rmse"])


def test_workers_option_starts_worker_processes_on_one_study(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``sweep.workers=2``: one command, two processes (this one and a started one) share the study;
    the summary waits for both, and every counted trial has its child run under the one parent."""
    monkeypatch.chdir(user_project)
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=6", "sweep.pruner=none",
                           "sweep.workers=2", "sweep.study_name=two")) == 0
    study = load_study(user_project, "two")
    counted = [t for t in study.get_trials() if t.state.name == "COMPLETE"]
    assert len(counted) == 6 and not [t for t in study.get_trials() if t.state.name == "RUNNING"]
    pids = {t.user_attrs[sw.WORKER_ATTR]["pid"] for t in counted}
    assert os.getpid() in pids and len(pids) == 2  # this process and the one it started
    store, _ = open_stores(user_project)
    (parent,) = sweep_parents(store)
    assert parent.info.status == "FINISHED"
    assert sorted(k.info.run_id for k in children(store, parent.info.run_id)) == sorted(t.user_attrs[sw.RUN_ID_ATTR] for t in counted)


def test_workers_option_needs_the_command_line(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = compose([*TINY, "sweep.space=small", "sweep.workers=2"], user_config_dir=user_project / "my_conf")
    with pytest.raises(ConfigError, match=r"sweep.workers=2 starts worker processes from the command line"):
        stage.run(cfg)
    assert not (user_project / "mlflow.db").exists() and not (user_project / "optuna.db").exists()  # nothing written


def test_grouped_trials_train_as_one_stack_and_each_keeps_its_own_run(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``sweep.group=3``: trials asked three at a time and trained in one batched solve; every
    trial still gets its own child run with its own per-epoch metrics, and its weights reload to
    the logged validation RMSE. While fewer than ``pruner_startup_trials`` (here 2) trials are
    complete, a group holds only the missing ones (the pruner has nothing to compare with)."""
    from physmend.tracking import load_trial
    from physmend.ude import evaluate

    monkeypatch.chdir(user_project)
    assert main(sweep_args(user_project, "sweep.space=small", "sweep.n_trials=5", "sweep.group=3",
                           "sweep.pruner_startup_trials=2", "sweep.study_name=grouped")) == 0
    study = load_study(user_project, "grouped")
    trials = study.get_trials()
    assert [t.state.name for t in trials[:2]] == ["COMPLETE"] * 2
    assert {t.state.name for t in trials[2:]} <= {"COMPLETE", "PRUNED"}
    # groups of 2 (the startup trials), then 3: a trial's start time is its group's
    starts = [t.datetime_start for t in trials]
    assert starts[0] <= starts[1] < starts[2] <= starts[3] <= starts[4]
    assert max(t.datetime_complete for t in trials[:2]) <= starts[2]
    store, _ = open_stores(user_project)
    kids = children(store, study.user_attrs[sw.PARENT_ATTR])
    assert [k.info.run_name.lstrip("★ ")[:10] for k in kids] == [f"trial-000{i}" for i in range(5)]
    # sweep.group_shapes (default): a group's trials share the first one's width (the small space's
    # only shape key); the sampler proposes the rest freely
    assert sw.shape_keys(sw.load_space("small")) == ["ude.width"]
    for group in (trials[:2], trials[2:]):
        assert len({t.params["ude.width"] for t in group}) == 1
        assert len({t.params["train.lr"] for t in group}) == len(group)
    for trial, kid in zip(trials, kids):
        assert kid.data.tags["physmend.stacked"] == "true"
        assert kid.data.tags["physmend.trial_state"] == trial.state.name
        assert kid.data.params == {k: str(v) for k, v in trial.params.items()}
        if trial.state.name != "COMPLETE":
            continue
        assert kid.data.metrics["val.rmse"] == pytest.approx(trial.value, rel=1e-12)
        steps = [m.step for m in store.client.get_metric_history(kid.info.run_id, "val.rmse")]
        assert steps == [0, 2, 4, 6, 7]  # warm start, epochs 2 and 4, the L-BFGS polish, the final value
        assert trial.intermediate_values and set(trial.intermediate_values) == {0, 2, 4, 6}  # 6: the L-BFGS polish
        # the final metrics come from one batched solve of the stack's models: a reloaded model
        # evaluated on its own agrees to the solver tolerance
        loaded = load_trial(store, kid.info.run_id)
        assert evaluate(loaded.hybrid, loaded.problem, loaded.cfg)["val.rmse"] == pytest.approx(kid.data.metrics["val.rmse"], rel=1e-3)
