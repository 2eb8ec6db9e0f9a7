"""A standby worker told its sweep ahead (:func:`physmend.sweep.standby.brief`) prepares what the
command does before its first trial while it waits: the stores' modules imported (no store opened),
the model compiled and kept for the command; a preparation that fails costs nothing but time, and
the command line handed afterwards runs. Real processes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from physmend import prestart
from physmend import problem as problem_module
from physmend.config import compose
from physmend.problem import load_problem
from physmend.sweep import standby

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=10",
        "train.eval_every=5", "simulate.rtol=1e-6", "simulate.atol=1e-7", "ude.depth=1"]


def test_the_preparation_compiles_the_model_the_command_then_reuses(monkeypatch: pytest.MonkeyPatch) -> None:
    compiled: list[int] = []
    real = problem_module.compile_model
    monkeypatch.setattr(problem_module, "compile_model", lambda *a, **k: compiled.append(1) or real(*a, **k))
    problem_module._COMPILED.clear()
    standby._prepare({"overrides": TINY, "config_dir": None})
    assert compiled == [1] and len(problem_module._COMPILED) == 1  # compiled once, and kept in this process
    problem = load_problem(compose(TINY))  # what the command does before its first trial: nothing compiled again
    assert compiled == [1] and problem.compiled.state_names == ["mass.x", "mass.v"]


def test_preloading_the_stores_imports_their_modules_and_opens_none(tmp_path: Path) -> None:
    code = ("import sys; from physmend.tracking.store import STORE_MODULES, preload; preload(); "
            "print(all(m in sys.modules for m in STORE_MODULES))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "True", out.stderr
    assert not list(tmp_path.iterdir())  # no store, no file


def test_a_preparation_that_fails_costs_nothing_and_the_command_line_still_runs() -> None:
    standby._prepare({"overrides": ["no_such_group=1"], "config_dir": None})  # swallowed: the command reports it
    procs = prestart.spawn(1)
    try:
        standby.brief(procs, ["no_such_group=1"], "/nonexistent/folder")
        standby.brief(procs, TINY, None)  # several briefs: each prepared in turn
        assert standby.hand(procs[0], ["--version"], {}) is procs[0]
        assert procs[0].wait(timeout=300) == 0
    finally:
        standby.release(procs)
    released = prestart.spawn(1)
    standby.brief(released, TINY, None)
    standby.release(released)  # briefed, never handed a command line: ended
    assert released[0].poll() is not None


def test_a_standby_process_runs_the_command_line_after_its_brief() -> None:
    proc = subprocess.Popen([sys.executable, "-m", "physmend.sweep.standby"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    standby.brief([proc], TINY, None)
    standby.hand(proc, ["--version"], {})
    assert proc.stdout is not None
    out = proc.stdout.read()
    proc.wait(timeout=300)
    from physmend import __version__

    assert proc.returncode == 0 and out.strip() == __version__
