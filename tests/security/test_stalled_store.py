"""A database server that accepts the TCP connection and never answers (a real socket here, see
``silent_server``) stops ``physmend ui`` and every stage opening the store within seconds, in one
line naming the key and the store without its password, exit 2, whatever the SQLAlchemy dialect
physmend accepts: a driver that is installed is given up on after the deadline, one that is not is
named with what to install."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import sqlalchemy

from physmend.tracking.store import SERVER_TIMEOUT_S
from physmend.tracking.ui import PROBE_TIMEOUT

from .conftest import physmend_command

PASSWORD = "pw'4711:x"
#: every dialect physmend stores runs in, with its default driver and another one
DIALECTS = ["postgresql", "postgresql+psycopg2", "mysql", "mysql+pymysql", "mssql", "mssql+pymssql"]
#: seconds a process may need to start and compose its configuration on a loaded 2-core machine
START_S = 8


def _uri(dialect: str, port: int) -> str:
    return f"{dialect}://alice:{PASSWORD}@127.0.0.1:{port}/mlflow"


def _expected(uri: str, timeout: int) -> str:
    """What the line must say: the deadline when the dialect's driver is installed, else its name."""
    try:
        sqlalchemy.engine.make_url(uri).get_dialect().import_dbapi()
    except ModuleNotFoundError as exc:
        return f"its database driver {exc.name.split('.')[0]!r} is not installed"
    return f"no answer within {timeout} s"


def _one_line(err: str, *words: str) -> str:
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line and len(line) <= 300, err
    assert PASSWORD not in line and "alice:***@127.0.0.1:" in line, line
    for word in words:
        assert word in line, (word, line)
    return line


def test_ui_gives_up_on_a_server_that_never_answers(silent_server: int, tmp_path: Path) -> None:
    uri = _uri("postgresql+psycopg2", silent_server)
    start = time.perf_counter()
    done = subprocess.run([*physmend_command(), "ui", f"tracking.uri=\"{uri}\""], cwd=tmp_path, capture_output=True,
                          text=True, timeout=PROBE_TIMEOUT + START_S + 30)
    assert time.perf_counter() - start < PROBE_TIMEOUT + START_S
    assert done.returncode == 2, done.stderr
    _one_line(done.stderr, "physmend ui: error: tracking.uri", _expected(uri, PROBE_TIMEOUT))
    assert "running:" not in done.stdout  # refused before the server's command


@pytest.mark.parametrize("dialect", DIALECTS)
def test_a_stage_gives_up_on_a_server_that_never_answers(dialect: str, silent_server: int, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch,
                                                         run_cli: Callable[..., tuple[int, str]]) -> None:
    monkeypatch.chdir(tmp_path)
    uri = _uri(dialect, silent_server)
    start = time.perf_counter()
    rc, err = run_cli("runs", f"tracking.uri=\"{uri}\"")
    assert time.perf_counter() - start < SERVER_TIMEOUT_S + 3
    assert rc == 2, err
    _one_line(err, "physmend runs: error: tracking.uri", "cannot be opened", _expected(uri, SERVER_TIMEOUT_S))
    assert list(tmp_path.iterdir()) == []


def test_a_sweep_gives_up_on_a_study_storage_that_never_answers(silent_server: int, user_project: Path,
                                                                monkeypatch: pytest.MonkeyPatch,
                                                                run_cli: Callable[..., tuple[int, str]]) -> None:
    monkeypatch.chdir(user_project)
    uri = _uri("postgresql+psycopg2", silent_server)
    start = time.perf_counter()
    rc, err = run_cli("sweep", "--config-dir", str(user_project / "my_conf"), "model=oscillator", "data=oscillator",
                      f"tracking.optuna_storage=\"{uri}\"")
    assert time.perf_counter() - start < SERVER_TIMEOUT_S + START_S
    assert rc == 2, err
    _one_line(err, "physmend sweep: error: tracking.optuna_storage", _expected(uri, SERVER_TIMEOUT_S))
