"""``physmend ui`` keeps the store's password off every command line (the MLflow child reads the store
from its environment, which only the user's own processes can read) and checks the store with a short
timeout before it starts a server: a store that does not answer is one line, at once, without the
password."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import pytest

PASSWORD = "s3cr@t:4711"
URI = f"postgresql://alice:{PASSWORD}@127.0.0.1:9/mlflow"


def test_the_child_gets_the_store_in_its_environment_not_its_command_line() -> None:
    from physmend.tracking.ui import STORE_VARIABLE, server_command

    cmd, env = server_command(URI, "127.0.0.1", 5000)
    assert not any(PASSWORD in word or "alice" in word for word in cmd), cmd
    assert cmd[1:4] == ["-m", "mlflow", "ui"] and "--backend-store-uri" not in cmd
    assert env[STORE_VARIABLE] == URI


def test_an_unreachable_store_is_one_line_at_once_and_no_server_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                      run_cli: Callable[..., tuple[int, str]],
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    start = time.perf_counter()
    rc, err = run_cli("ui", f"tracking.uri='{URI}'")
    assert time.perf_counter() - start < 10
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line and len(line) <= 300, line
    assert PASSWORD not in line and "alice:***@127.0.0.1:9" in line and "cannot be opened" in line
    assert "running:" not in capsys.readouterr().out  # refused before the server's command


def test_a_missing_store_folder_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            run_cli: Callable[..., tuple[int, str]]) -> None:
    monkeypatch.chdir(tmp_path)
    rc, err = run_cli("ui", f"tracking.uri=sqlite:///{tmp_path}/no/such/mlflow.db")
    assert rc == 2 and "does not exist" in err and len(err.strip().splitlines()) == 1, err
