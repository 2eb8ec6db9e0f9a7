"""Every bad value, store or path a new user is likely to give ends in one clear line on stderr
(at most 3 lines, no traceback), exit status 2, and leaves the user's data, model file and stores
exactly as they were."""

from __future__ import annotations

import hashlib
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from physmend.cli import main

Setup = Callable[[Path], list[str]]


def _tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _override(*items: str) -> Setup:
    return lambda project: list(items)


def _corrupt_store(project: Path) -> list[str]:
    (project / "mlflow.db").write_bytes(b"this is not a database\n" * 64)
    return []


def _raising_builder(project: Path) -> list[str]:
    (project / "broken.py").write_text(textwrap.dedent('''
        from physmend.modeling import Model

        def build():
            m = Model("broken")
            raise ValueError("spring constant must be positive")  # the user's own check
    '''))
    (project / "my_conf" / "model" / "broken.yaml").write_text(f"builder: {project / 'broken.py'}:build\noptions: {{}}\n")
    return ["model=broken"]


def _syntax_error_builder(project: Path) -> list[str]:
    (project / "typo.py").write_text("def build(:\n    pass\n")
    (project / "my_conf" / "model" / "typo.yaml").write_text(f"builder: {project / 'typo.py'}:build\noptions: {{}}\n")
    return ["model=typo"]


CASES: list[tuple[str, str, Setup, list[str]]] = [
    # (id, command, setup, words the one line must contain)
    ("n_windows", "diagnose", _override("diagnose.n_windows=abc"), ["diagnose.n_windows", "'abc'", "whole number"]),
    ("rtol", "diagnose", _override("simulate.rtol=abc"), ["simulate.rtol", "'abc'", "number > 0"]),
    ("epochs", "sweep", _override("train.epochs=abc"), ["train.epochs", "'abc'"]),
    ("negative lr", "sweep", _override("train.lr=-0.01"), ["train.lr", "-0.01", "> 0"]),
    ("schedule", "sweep", _override("train.schedule=linear"), ["train.schedule", "cosine", "'linear'"]),
    ("switch", "diagnose", _override("diagnose.plots=maybe"), ["diagnose.plots", "true or false"]),
    ("unknown operator", "diagnose", _override("+operators.cosine=1"), ["operators", "default.yaml", "'cosine'"]),
    ("negative price", "diagnose", _override("operators.mul=-2"), ["default.yaml", "'mul'", "-2"]),
    ("unknown option", "diagnose", _override("model=nosuch"), ["model=nosuch", "the options are", "oscillator"]),
    ("unknown key", "sweep", _override("train.nosuch=1"), ["train.nosuch", "+train.nosuch=1"]),
    ("unknown scheme", "diagnose", _override("tracking.uri=foo://bar"), ["tracking.uri", "foo://bar"]),
    ("missing folder", "diagnose", _override("tracking.uri=sqlite:////no/such/folder/mlflow.db"),
     ["tracking.uri", "/no/such/folder"]),
    ("unwritable folder", "diagnose", _override("tracking.uri=sqlite:////proc/self/mlflow.db"),
     ["tracking.uri", "/proc/self"]),
    ("corrupt store", "diagnose", _corrupt_store, ["mlflow.db"]),
    ("no server", "diagnose", _override("tracking.uri=http://127.0.0.1:9"), ["tracking.uri", "127.0.0.1:9"]),
    ("builder raises", "diagnose", _raising_builder, ["broken.py", "line", "spring constant must be positive"]),
    ("builder syntax", "diagnose", _syntax_error_builder, ["typo.py", "line 1"]),
    ("device word", "sweep", _override("device=gpu"), ["device", "'gpu'", "cuda:N"]),
    *([("no cuda", "sweep", _override("device=cuda"), ["device=cuda", "no CUDA device", "device=cpu"])]
      if not torch.cuda.is_available() else []),
]


@pytest.mark.parametrize("command, setup, words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_nothing_changes(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str], command: str,
                                                         setup: Setup, words: list[str]) -> None:
    monkeypatch.chdir(user_project)
    extra = setup(user_project)
    before = _tree(user_project)
    base = [o for o in ("model=oscillator", "data=oscillator") if o.split("=")[0] not in {e.split("=")[0] for e in extra}]
    rc = main([command, "--config-dir", str(user_project / "my_conf"), *base, *extra])
    out = capsys.readouterr()
    assert rc == 2, out.err + out.out
    lines = out.err.strip().splitlines()
    assert 1 <= len(lines) <= 3 and "Traceback" not in out.err, out.err
    for word in words:
        assert word in out.err, (word, out.err)
    assert _tree(user_project) == before  # data, model files, stores: byte for byte
