"""A refusal costs what the check costs: an error raised before the heavy libraries were needed is
reported without importing them (``physmend.errors`` names the user errors instead of importing
their modules: torch, pandas, sympy and MLflow were 2 s of every command's start, 4 s under load),
and which errors are the user's is exactly what it was."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from physmend.errors import USER_ERROR_NAMES, USER_ERRORS, is_user_error

HEAVY = ("torch", "mlflow", "pandas", "sympy", "optuna")


def test_the_named_user_errors_are_exactly_the_classes() -> None:
    assert {(c.__module__, c.__qualname__) for c in USER_ERRORS} == set(USER_ERROR_NAMES)
    for cls in USER_ERRORS:
        assert issubclass(cls, Exception) and is_user_error(cls.__new__(cls)), cls
        sub = type("Sub", (cls,), {})
        assert is_user_error(sub.__new__(sub)), cls
    for other in (ValueError("x"), RuntimeError("x"), KeyError("x"), KeyboardInterrupt(), OSError(28, "full")):
        assert not is_user_error(other), other


@pytest.mark.parametrize("argv", [
    ["runs", "tracking.uri=sqlite:///{tmp}/not-a-database.db"],  # a store that cannot be opened
    ["ui", "tracking.uri=sqlite:///{tmp}/not-a-database.db"],
    ["runs", "tracking.uri=sqlite:///{tmp}/no/such/folder/mlflow.db"],
    ["diagnose", "train.epochs=abc"],  # a setting of the wrong kind
])
def test_a_refusal_before_any_work_imports_no_heavy_library(argv: list[str], tmp_path: Path) -> None:
    (tmp_path / "not-a-database.db").write_bytes(b"this is not a database\n" * 64)
    words = [w.format(tmp=tmp_path) for w in argv]
    code = ("import sys\nfrom physmend.cli import main\nrc = main(sys.argv[1:])\n"
            f"print('loaded:', *[m for m in {HEAVY!r} if m in sys.modules])\nsys.exit(rc)")
    done = subprocess.run([sys.executable, "-c", code, *words], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "loaded:", done.stdout
