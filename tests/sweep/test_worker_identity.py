"""Two real sweep worker processes that report the same host name and the same PID (as workers in
two containers may) share one study: neither marks the other's running trial stale.

Each worker is a separate Python process started from a launcher that replaces ``os.getpid``,
``socket.gethostname`` and ``platform.node`` with fixed values before ``physmend.cli.main`` runs.
The fixed PID is this test process's own (alive), so only the worker's random ID can tell the two
apart: with an identity of host name and PID each would judge the other's running trial its own
(stale at once) and mark it FAIL (interrupted). Real (tiny) training on the oscillator of
tests/conftest.py, real MLflow and Optuna sqlite stores in a temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

import physmend.sweep as sw

HOST = "twin-container"
STUDY = "twins"
N_TRIALS = 4

TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=4", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.progress=false", "sweep.figures=false", "sweep.space=small", "sweep.pruner=none",
    f"sweep.study_name={STUDY}", f"sweep.n_trials={N_TRIALS}",
    # heartbeats of a live trial are fresh; a trial judged by host and PID would be stale at once
    "sweep.heartbeat_interval=1", "sweep.stale_after=3",
]

# argv: fixed PID, host name, ready file, go file, then the `physmend` arguments
LAUNCHER = textwrap.dedent(
    """
    import os, platform, socket, sys, time
    from pathlib import Path

    pid, host, ready, go = int(sys.argv[1]), sys.argv[2], Path(sys.argv[3]), Path(sys.argv[4])
    os.getpid = lambda: pid
    socket.gethostname = lambda: host
    platform.node = lambda: host
    from physmend.cli import main
    from physmend.sweep import workers

    assert workers.this_worker()["pid"] == pid and workers.this_worker()["host"] == host
    ready.touch()
    deadline = time.monotonic() + 120
    while not go.exists():  # both workers start their sweeps together
        if time.monotonic() > deadline:
            sys.exit("no go")
        time.sleep(0.02)
    sys.exit(main(sys.argv[5:]))
    """
)


def _children(store: Any) -> tuple[Any, list[Any]]:
    runs = store.client.search_runs([store.experiment_id], "tags.`physmend.stage` = 'sweep'")
    assert len(runs) == 1, [r.data.tags for r in runs]  # one parent run for the one study
    parent = runs[0]
    return parent, store.client.search_runs([store.experiment_id], f"tags.`mlflow.parentRunId` = '{parent.info.run_id}'")


def test_two_workers_with_one_host_name_and_pid_share_a_study_without_stale_trials(user_project: Path) -> None:
    import optuna
    from optuna.trial import TrialState

    from physmend.tracking import open_store

    fake_pid = os.getpid()  # alive for the whole test: a dead PID in this namespace would be stale for another reason
    args = ["sweep", "--config-dir", str(user_project / "my_conf"), *TINY]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    go = user_project / "go"
    readies = [user_project / f"ready{i}" for i in range(2)]
    procs = [
        subprocess.Popen([sys.executable, "-c", LAUNCHER, str(fake_pid), HOST, str(ready), str(go), *args],
                         cwd=user_project, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for ready in readies
    ]
    try:
        deadline = time.monotonic() + 120
        while not all(r.exists() for r in readies):
            assert time.monotonic() < deadline and all(p.poll() is None for p in procs), "a worker did not start"
            time.sleep(0.05)
        go.touch()
        results = [p.communicate(timeout=240) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for p, (out, err) in zip(procs, results):
        assert p.returncode == 0, err[-3000:]
        assert "was left running by worker" not in err, err[-3000:]
        assert "could not record the result" not in err, err[-3000:]

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    trials = optuna.load_study(study_name=STUDY, storage=f"sqlite:///{user_project / 'optuna.db'}").get_trials()
    # a surplus trial (both asked for the last one at once) is a legitimate race, not a verdict
    surplus = [t for t in trials if t.state == TrialState.FAIL and t.user_attrs.get(sw.REASON_ATTR) == "surplus"]
    counted = [t for t in trials if t not in surplus]
    assert all(t.state == TrialState.COMPLETE for t in counted), [(t.number, t.state.name, t.user_attrs.get(sw.REASON_ATTR)) for t in counted]
    assert len(counted) == N_TRIALS
    assert not [t for t in trials if t.user_attrs.get(sw.REASON_ATTR) == "interrupted"]

    # both workers recorded the same host name and PID, yet different worker IDs, and both ran trials
    identities = [t.user_attrs[sw.WORKER_ATTR] for t in counted]
    assert {(w["host"], w["pid"]) for w in identities} == {(HOST, fake_pid)}
    ids = {w["id"] for w in identities}
    assert len(ids) == 2 and all(isinstance(i, str) and len(i) == 32 for i in ids), ids
    # and they ran at the same time: a worker asked for a trial (after looking for stale ones) while
    # a trial of the other worker was running
    overlap = [
        (x.number, y.number) for x in counted for y in counted
        if x.user_attrs[sw.WORKER_ATTR]["id"] != y.user_attrs[sw.WORKER_ATTR]["id"]
        and y.datetime_start < x.datetime_start < y.datetime_complete
    ]
    assert overlap, [(t.number, t.datetime_start, t.datetime_complete) for t in counted]

    # one MLflow child run per trial, the one the trial records, finished
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{user_project / 'mlflow.db'}", "experiment": "physmend"}))
    parent, kids = _children(store)
    assert parent.info.status == "FINISHED"
    assert len(kids) == N_TRIALS
    by_number = {int(k.data.tags["physmend.trial_number"]): k for k in kids}
    assert sorted(by_number) == sorted(t.number for t in counted)
    for t in counted:
        kid = by_number[t.number]
        assert kid.info.run_id == t.user_attrs[sw.RUN_ID_ATTR]
        assert kid.info.status == "FINISHED" and kid.data.tags["physmend.trial_state"] == "COMPLETE"
