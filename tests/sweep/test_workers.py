"""Worker identity: workers in different containers may share a host name and a PID; only their
random worker ID, their namespace and their heartbeat say whether a running trial is stale."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import optuna

import physmend.sweep as sw
from physmend.sweep import workers


def _study(tmp_path: Path) -> optuna.Study:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna.create_study(study_name="s", storage=f"sqlite:///{tmp_path / 'optuna.db'}")


def test_two_workers_with_one_host_name_and_pid_do_not_mark_each_other_stale(tmp_path: Path) -> None:
    study = _study(tmp_path)
    me = workers.this_worker()
    assert me["id"] == workers.WORKER_ID and len(me["id"]) == 32
    # another container: same host name, same PID, another worker ID and PID namespace, beating
    other = {**me, "id": "f" * 32, "ns": "another-boot:4026531836"}
    theirs = study.ask()
    theirs.set_user_attr(sw.WORKER_ATTR, other)
    theirs.set_user_attr(sw.HEARTBEAT_ATTR, time.time())
    (frozen,) = [t for t in study.get_trials() if t.number == theirs.number]
    assert not sw.is_stale(frozen, now=time.time(), stale_after=300, me=me)
    # ... until its heartbeat stops for longer than stale_after
    assert sw.is_stale(frozen, now=time.time() + 301, stale_after=300, me=me)
    # this process's own earlier trial is stale at once (it runs none while it asks)
    mine = study.ask()
    mine.set_user_attr(sw.WORKER_ATTR, me)
    mine.set_user_attr(sw.HEARTBEAT_ATTR, time.time())
    (frozen_mine,) = [t for t in study.get_trials() if t.number == mine.number]
    assert sw.is_stale(frozen_mine, now=time.time(), stale_after=300, me=me)


def test_a_dead_worker_in_the_same_namespace_is_stale_at_once(tmp_path: Path) -> None:
    study = _study(tmp_path)
    me = workers.this_worker()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for pid, stale in ((dead.pid, True), (workers.os.getppid(), False)):
        t = study.ask()
        t.set_user_attr(sw.WORKER_ATTR, {**me, "id": f"{pid:032d}", "pid": pid})
        t.set_user_attr(sw.HEARTBEAT_ATTR, time.time())
        (frozen,) = [x for x in study.get_trials() if x.number == t.number]
        assert sw.is_stale(frozen, now=time.time(), stale_after=300, me=me) is stale


def test_a_new_process_draws_a_new_worker_id() -> None:
    code = "from physmend.sweep import workers; print(workers.WORKER_ID)"
    ids = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
           for _ in range(2)}
    assert len(ids) == 2 and workers.WORKER_ID not in ids


def test_the_caller_s_work_for_later_runs_once_and_its_failure_is_not_the_sweep_s() -> None:
    """``Sweep.idle``: the ``meanwhile`` work runs the first time a worker waits, never again; an
    exception from it stays there (the stage it prepares does that work again and reports it)."""
    from physmend.sweep.loop import Sweep

    calls: list[str] = []

    def work() -> None:
        calls.append("ran")
        raise RuntimeError("the later stage would report this")

    sweep = Sweep(*([None] * 9), meanwhile=work)
    sweep.idle()
    sweep.idle()
    assert calls == ["ran"] and sweep.meanwhile is None
    Sweep(*([None] * 9)).idle()  # nothing to do: nothing happens
