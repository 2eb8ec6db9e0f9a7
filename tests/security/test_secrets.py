"""A password given in a store URI is used to open the store and nowhere else: not in the run's
config, parameters or tags, not in the MLflow database or artifacts, not on stdout or stderr."""

from __future__ import annotations

from pathlib import Path

import pytest

from physmend.cli import main
from physmend.redact import redact

PASSWORD = "s3cretPW-4711"


def _grep_tree(root: Path, needle: str) -> list[str]:
    return [str(p) for p in root.rglob("*") if p.is_file() and needle.encode() in p.read_bytes()]


@pytest.mark.parametrize("text, expected", [
    (f"postgresql://alice:{PASSWORD}@db.example:5432/optuna", "postgresql://alice:***@db.example:5432/optuna"),
    (f"tracking.uri 'mysql+pymysql://bob:p@ss:w/rd@db/x' cannot be opened", "tracking.uri 'mysql+pymysql://bob:***@db/x' cannot be opened"),
    (f"https://:{PASSWORD}@mlflow.example", "https://:***@mlflow.example"),
    (f"http://host/x?user=a&password={PASSWORD}&b=1", "http://host/x?user=a&password=***&b=1"),
    ("sqlite:///tmp/mlflow.db and http://mlflow.example:5000/ and postgresql://alice@db/x",
     "sqlite:///tmp/mlflow.db and http://mlflow.example:5000/ and postgresql://alice@db/x"),
])
def test_redact_keeps_the_user_and_drops_the_password(text: str, expected: str) -> None:
    assert redact(text) == expected


def test_a_password_in_a_storage_uri_is_never_stored_or_printed(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(user_project)
    storage = f"postgresql://alice:{PASSWORD}@db.example:5432/optuna"
    args = ["--config-dir", str(user_project / "my_conf"), "model=oscillator", "data=oscillator",
            f"tracking.optuna_storage={storage}"]
    assert main(["diagnose", *args]) == 0
    assert main(["config", *args]) == 0
    assert main(["runs", "--json", *args]) == 0
    out = capsys.readouterr()
    assert PASSWORD not in out.out + out.err
    assert "postgresql://alice:***@db.example:5432/optuna" in out.out  # `physmend config` shows where, not the secret
    assert (user_project / "mlflow.db").is_file()
    assert _grep_tree(user_project, PASSWORD) == []  # database, artifacts, anything written in the project


def test_an_unreachable_store_with_a_password_is_one_line_without_it(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(user_project)
    rc = main(["diagnose", "--config-dir", str(user_project / "my_conf"), "model=oscillator", "data=oscillator",
               f"tracking.uri=postgresql://alice:{PASSWORD}@127.0.0.1:9/mlflow"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert PASSWORD not in err and "alice:***@127.0.0.1:9" in err
    assert len(err.strip().splitlines()) <= 3 and "Traceback" not in err
    assert _grep_tree(user_project, PASSWORD) == []
