"""Scale-out as docs/many-machines.md describes it: a real PostgreSQL (this machine's ``initdb`` /
``pg_ctl``, on a free loopback port), a real ``mlflow server`` process on it with proxied
artifacts, Optuna on the same PostgreSQL, and two ``physmend sweep`` worker processes joining one
study. Every trial is in Optuna and in MLflow exactly once, and a trial's artifacts come back
through the server. Skips only where no PostgreSQL binaries or no ``psycopg2`` exist.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared helpers  # noqa: E402
from mlflow_servers import free_port, mlflow_server as serve_mlflow  # noqa: E402

N_TRIALS = 4
TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=4", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.progress=false", "sweep.figures=false", "sweep.space=small", "sweep.pruner=none",
    "sweep.study_name=shared", f"sweep.n_trials={N_TRIALS}",
]


@pytest.fixture
def postgres() -> Iterator[str]:
    """A PostgreSQL server in a temporary folder: yields ``host:port`` (user postgres, trust auth)."""
    initdb, pg_ctl = shutil.which("initdb"), shutil.which("pg_ctl")
    if not initdb or not pg_ctl:
        pytest.skip("no PostgreSQL binaries (initdb, pg_ctl) on this machine")
    pytest.importorskip("psycopg2", reason="psycopg2 is not installed (pip install -e '.[test]')")
    import tempfile

    as_user: list[str] = []
    # outside pytest's folder (its parents are private to this user: another user's server cannot enter)
    data = Path(tempfile.mkdtemp(prefix="physmend-pg-"))
    if os.geteuid() == 0:  # initdb refuses to run as root: run the server as the postgres user
        import pwd

        try:
            pw = pwd.getpwnam("postgres")
        except KeyError:
            shutil.rmtree(data)
            pytest.skip("running as root and no 'postgres' user to run PostgreSQL as")
        os.chown(data, pw.pw_uid, pw.pw_gid)
        as_user = ["runuser", "-u", "postgres", "--"]
    port = free_port()
    subprocess.run([*as_user, initdb, "-D", str(data / "db"), "-U", "postgres", "--auth=trust", "-E", "UTF8"],
                   check=True, capture_output=True)
    subprocess.run([*as_user, pg_ctl, "-D", str(data / "db"), "-o", f"-p {port} -k {data} -c listen_addresses=127.0.0.1",
                    "-l", str(data / "log"), "-w", "start"], check=True, capture_output=True)
    try:
        import psycopg2

        conn = psycopg2.connect(host="127.0.0.1", port=port, user="postgres", dbname="postgres")
        conn.autocommit = True
        with conn.cursor() as cur:
            cur.execute("CREATE DATABASE mlflow")
            cur.execute("CREATE DATABASE optuna")
        conn.close()
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([*as_user, pg_ctl, "-D", str(data / "db"), "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(data, ignore_errors=True)


@pytest.fixture
def mlflow_server(postgres: str, tmp_path: Path) -> Iterator[str]:
    """``mlflow server`` on the PostgreSQL above, artifacts proxied to a folder: yields its URL."""
    with serve_mlflow(f"postgresql+psycopg2://postgres@{postgres}/mlflow", tmp_path / "server-artifacts", tmp_path,
                       tmp_path / "mlflow-server.log") as url:
        yield url


@pytest.mark.slow
def test_two_workers_share_one_study_on_postgresql_and_an_mlflow_server(user_project: Path, postgres: str,
                                                                       mlflow_server: str) -> None:
    import optuna
    from mlflow.tracking import MlflowClient

    storage = f"postgresql+psycopg2://postgres@{postgres}/optuna"
    common = ["--config-dir", str(user_project / "my_conf"), *TINY, f"tracking.uri={mlflow_server}",
              f"tracking.optuna_storage={storage}"]
    # two machines: two folders, nothing shared but the servers
    procs = []
    for k in range(2):
        folder = user_project / f"machine{k}"
        folder.mkdir()
        procs.append(subprocess.Popen([sys.executable, "-m", "physmend.cli", "sweep", *common], cwd=folder,
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], "\n".join(o[-3000:] for o in outs)
    for k in range(2):  # no stray local store or artifacts on either machine
        assert sorted(p.name for p in (user_project / f"machine{k}").iterdir()) == [], k

    study = optuna.load_study(study_name="shared", storage=storage)
    states = [t.state for t in study.trials]
    assert len(states) == N_TRIALS and all(s == optuna.trial.TrialState.COMPLETE for s in states), states
    client = MlflowClient(tracking_uri=mlflow_server)
    exp = client.get_experiment_by_name("physmend")
    runs = client.search_runs([exp.experiment_id], filter_string="tags.`physmend.stage` = 'trial'")
    numbers = sorted(int(r.data.tags["physmend.trial_number"]) for r in runs)
    assert numbers == sorted(t.number for t in study.trials), numbers  # each trial exactly once
    parents = {r.data.tags.get("mlflow.parentRunId") for r in runs}
    assert len(parents) == 1 and None not in parents  # the study's first worker made the parent run; both use it
    # a trial's artifacts come back through the server (proxied), not from a path on one machine
    first = runs[0].info.run_id
    listed = {a.path for a in client.list_artifacts(first)}
    assert listed, first
    got = Path(client.download_artifacts(first, sorted(listed)[0], str(user_project)))
    assert got.exists()
