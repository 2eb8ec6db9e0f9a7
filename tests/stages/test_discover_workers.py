"""``physmend discover`` runs its sweep's first trials side by side (``discover.workers``, one trial
per process, ``discover.group: 1``): each trial is the one a single process trains, a key the
user gives is left out of the search in every process, and the budget counts rounds of trials
that ran at once (tests/sweep/test_budget.py). Real training, real Optuna and MLflow sqlite stores
in a temporary folder."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

import optuna
import pytest

from physmend.cli import main
from physmend.config import compose
from physmend.cpus import usable_cpus
from physmend.stages.discover import _workers, sweep_settings
from physmend.sweep.storage import REASON_ATTR, WORKER_ATTR

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=20",
        "train.eval_every=10", "simulate.rtol=1e-6", "simulate.atol=1e-7", "ude.depth=1", "sweep.figures=false",
        "sweep.progress=false"]
LONGER = [o if not o.startswith("train.epochs=") else "train.epochs=80" for o in TINY]


def _ready(procs: list, settle: float = 0.5, limit: float = 120.0) -> None:
    """Wait until every standby process of ``procs`` has imported and waits for its command line (no
    CPU time for ``settle`` s), as discover's have by its sweep (they import while diagnose runs): the
    first process's first trial would otherwise race a worker still importing under the suite's load."""
    for proc in procs:
        stat = Path(f"/proc/{proc.pid}/stat")
        if not stat.exists():  # no /proc: a worker's imports take seconds
            time.sleep(15.0)
            continue

        def cpu() -> int:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            return int(fields[11]) + int(fields[12])  # utime + stime, clock ticks

        start = last_change = time.monotonic()
        last = cpu()
        while time.monotonic() - start < limit and proc.poll() is None:
            time.sleep(0.1)
            now = cpu()
            if now != last:
                last, last_change = now, time.monotonic()
            elif time.monotonic() - last_change >= settle:
                break


def _sweep_beside_standby(overrides: list[str], conf: Path, extra: int, meanwhile: Callable[[], None] | None = None) -> list:
    """discover's sweep (``given_wins``) run beside ``extra`` standby processes started before it and
    ready, as discover's are, with discover's ``meanwhile`` work; returns the standby processes
    (ended or handed their command line)."""
    from physmend.stages import sweep
    from physmend.sweep import standby

    early = standby.start(extra)
    try:
        _ready(early)
        sweep.run(compose(overrides, user_config_dir=conf), None, overrides=overrides, config_dir=conf,
                  given_wins=True, standby=early, meanwhile=meanwhile)
    finally:
        standby.release(early)
    return early


def test_auto_is_the_cpus_at_most_the_first_trials() -> None:
    assert _workers("auto", 2) == min(usable_cpus(), 2)
    assert _workers("auto", 1) == 1  # one trial: one process
    assert _workers(3, 2) == 3  # a count as given


def test_discover_sets_the_sweep_s_workers_unless_the_command_line_does() -> None:
    cfg = sweep_settings(compose([]), [])
    assert cfg.sweep.group == 1 and cfg.sweep.workers == min(usable_cpus(), cfg.sweep.n_trials)
    assert sweep_settings(compose([]), None).sweep.workers == 1  # a direct call: no command line to start workers
    assert sweep_settings(compose(["sweep.workers=3"]), ["sweep.workers=3"]).sweep.workers == 3
    assert sweep_settings(compose(["discover.workers=1"]), ["discover.workers=1"]).sweep.workers == 1
    assert sweep_settings(compose(["sweep.n_trials=1"]), ["sweep.n_trials=1"]).sweep.workers == 1  # one trial


@pytest.mark.slow
def test_two_workers_train_the_trials_one_process_trains(
        user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """discover's sweep (``given_wins``, a budget) in two processes and in one: the same two trials, the
    same values, and the trials a stack of two would train; ``ude.width`` given on the command line
    is searched by no process (a worker that searched it would refuse the command line and end with
    an error); the second process is the one started before the sweep (:mod:`physmend.sweep.standby`).
    The caller's ``meanwhile`` work runs once in this process where another worker's trial keeps it
    waiting, and not at all where it trains every trial itself."""
    from physmend.stages import sweep

    monkeypatch.chdir(user_project)
    conf = user_project / "my_conf"
    values, params = {}, {}
    for workers in (2, 1):
        overrides = [*LONGER, "ude.width=8", "sweep.n_trials=2", "sweep.max_trials=2", "sweep.budget=100000",
                     "sweep.group=1", f"sweep.workers={workers}", f"sweep.study_name=w{workers}"]
        waited: list[int] = []
        early = _sweep_beside_standby(overrides, conf, workers - 1, meanwhile=lambda: waited.append(os.getpid()))
        assert waited == ([os.getpid()] if workers == 2 else [])
        out = capsys.readouterr()
        assert "ended with exit status" not in out.err  # no worker process failed
        assert "ude.width given on the command line" in out.out
        trials = optuna.load_study(study_name=f"w{workers}", storage=f"sqlite:///{user_project / 'optuna.db'}").trials
        assert [t.state.name for t in trials] == ["COMPLETE", "COMPLETE"]
        assert all("ude.width" not in t.params for t in trials)
        assert len({t.user_attrs[WORKER_ATTR]["id"] for t in trials}) == workers  # each process ran one trial
        assert {p.pid for p in early} <= {t.user_attrs[WORKER_ATTR]["pid"] for t in trials}
        values[workers] = [t.value for t in trials]
        params[workers] = [t.params for t in trials]
    assert params[2] == params[1] and params[1][0] != params[1][1]
    assert values[2] == pytest.approx(values[1], rel=1e-9)  # the same trials, trained alone either way
    # the trials a stack of two proposes (as discover's sweep did before its trials ran side by side)
    overrides = [*LONGER, "ude.width=8", "sweep.n_trials=2", "sweep.max_trials=2", "sweep.budget=100000",
                 "sweep.group=2", "sweep.group_shapes=false", "sweep.workers=1", "sweep.study_name=stack"]
    sweep.run(compose(overrides, user_config_dir=conf), None, overrides=overrides, config_dir=conf, given_wins=True)
    stacked = optuna.load_study(study_name="stack", storage=f"sqlite:///{user_project / 'optuna.db'}").trials
    assert [t.params for t in stacked] == params[1]


def test_standby_processes_not_needed_are_ended_and_dead_ones_replaced(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]) -> None:
    """A standby process runs the command line it is handed; one never handed any is ended by
    ``release``; one that ended before its turn is passed over and a new process started instead."""
    from physmend.sweep import standby
    from physmend.sweep.workers import _start_workers

    monkeypatch.chdir(tmp_path)
    ready = standby.start(1)
    try:
        proc = standby.hand(ready[0], ["--version"], {})
        assert proc is ready[0] and proc.wait(timeout=120) == 0  # ran `physmend --version`
    finally:
        standby.release(ready)
    unused = standby.start(1)
    standby.release(unused)
    assert unused[0].returncode is not None  # ended, having run nothing
    assert standby.hand(unused[0], ["--version"], {}) is None  # takes no command line any more
    started = _start_workers(1, None, ["sweep.n_trials=0"], None, standby=unused)
    assert len(started) == 1 and started[0] is not unused[0]  # a new process in its place
    assert started[0].wait(timeout=120) == 2  # which refuses the bad setting, as `physmend sweep` does
    assert "sweep.n_trials must be" in capfd.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing written


def test_a_budgeted_sweep_of_single_trials_enqueues_its_minimum_proposed_together(tmp_path: Path) -> None:
    """The study of a budgeted sweep with ``sweep.group: 1`` starts with its minimum enqueued, each
    trial's every value fixed: the first of ``first_trials`` as written plus what the sampler drew,
    then the sampler's proposals; every one of ``first_trials`` is kept where there are more of them
    than the minimum; without a budget only ``first_trials`` are enqueued, as before."""
    import physmend.sweep as sw
    from physmend.sweep.settings import proposed_together
    from physmend.sweep.storage import _study, open_storage

    space = sw.parse_space({"params": {"ude.width": {"choice": [8, 16, 32]}, "train.lr": {"log_uniform": [1e-3, 1e-1]}},
                            "first_trials": [{"ude.width": 8}, {"ude.width": 32, "train.lr": 0.01}, {"ude.width": 16}]},
                           name="mine", label="sweeps/mine.yaml")
    storage = open_storage(f"sqlite:///{tmp_path / 'optuna.db'}")

    def waiting(*overrides: str, name: str) -> list[dict]:
        settings = sw.Settings.from_cfg(compose(list(overrides)).sweep)
        study, created = _study(storage, name, settings, space, {})
        assert created
        return [t.system_attrs["fixed_params"] for t in study.get_trials(deepcopy=False)]

    settings = sw.Settings.from_cfg(compose(["sweep.budget=60", "sweep.n_trials=4", "sweep.group=1"]).sweep)
    proposed = proposed_together(space, settings, 4)
    assert waiting("sweep.budget=60", "sweep.n_trials=4", "sweep.group=1", name="four") == proposed
    assert [p["ude.width"] for p in proposed[:3]] == [8, 32, 16] and all(set(p) == {"ude.width", "train.lr"} for p in proposed)
    assert proposed == proposed_together(space, settings, 4)  # the same seed: the same proposals
    three = waiting("sweep.budget=60", "sweep.n_trials=2", "sweep.group=1", name="two")
    assert len(three) == 3 and [p["ude.width"] for p in three] == [8, 32, 16]  # every first trial kept
    assert waiting("sweep.n_trials=4", "sweep.group=1", name="count") == [dict(t) for t in space.first_trials]


@pytest.mark.slow
def test_after_the_budget_s_decision_every_worker_runs_its_share(
        user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Two workers, a minimum of two trials and a budget that allows two more: the worker whose first
    trial ends first waits for the decision (it comes when the other's ends) instead of leaving the
    two more to the other worker, so they run side by side, one in each process."""
    monkeypatch.chdir(user_project)
    conf = user_project / "my_conf"
    overrides = [*TINY, "ude.width=8", "sweep.n_trials=2", "sweep.max_trials=4", "sweep.budget=100000",
                 "sweep.group=1", "sweep.workers=2", "sweep.pruner=none", "sweep.study_name=rounds"]
    _sweep_beside_standby(overrides, conf, 1)
    assert "ended with exit status" not in capsys.readouterr().err
    trials = optuna.load_study(study_name="rounds", storage=f"sqlite:///{user_project / 'optuna.db'}").trials
    # a worker that asked at the same moment as the other for the minimum's last trial got a surplus
    # trial (a legitimate race, not a verdict) and went on waiting for the decision, not home
    counted = [t for t in trials if t.user_attrs.get(REASON_ATTR) != "surplus"]
    states = [(t.number, t.state.name, t.user_attrs.get(REASON_ATTR)) for t in trials]
    assert [t.state.name for t in counted] == ["COMPLETE"] * 4, states  # the budget allowed the most, 4
    later = counted[2:]
    assert len({t.user_attrs[WORKER_ATTR]["id"] for t in later}) == 2  # one in each process
    a, b = later
    assert a.datetime_start < b.datetime_complete and b.datetime_start < a.datetime_complete  # side by side
