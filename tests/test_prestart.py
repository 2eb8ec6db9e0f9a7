"""The standby worker the command line starts before composing discover's configuration: taken by
discover where its sweep wants an extra worker, ended otherwise — also when the command fails first.
Real processes."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from physmend import prestart
from physmend.cli import main
from physmend.sweep import standby


@pytest.fixture
def spawned(monkeypatch: pytest.MonkeyPatch) -> list[subprocess.Popen]:
    """Every standby process started during the test (the real ones, recorded)."""
    seen: list[subprocess.Popen] = []
    real = prestart.spawn

    def recording(count: int) -> list[subprocess.Popen]:
        procs = real(count)
        seen.extend(procs)
        return procs

    monkeypatch.setattr(prestart, "spawn", recording)
    return seen


def test_an_early_worker_is_taken_first_and_one_not_wanted_is_ended(spawned: list[subprocess.Popen]) -> None:
    prestart.start_early(1)
    first = spawned[0]
    try:
        taken = standby.start(2)
        assert taken[0] is first and len(taken) == 2 and len(spawned) == 2  # the early one, then one new
    finally:
        standby.release(spawned)
    prestart.start_early(1)
    assert standby.start(0) == []  # the configuration wants none: the early one is ended
    assert spawned[2].poll() is not None and not prestart._EARLY


def test_a_discover_that_fails_before_its_sweep_ends_its_early_worker(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spawned: list[subprocess.Popen],
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["discover", "discover.workers=banana"]) == 2
    assert "discover.workers" in capsys.readouterr().err
    assert not prestart._EARLY and all(p.poll() is not None for p in spawned)
    assert not list(tmp_path.iterdir())  # nothing written


def test_releasing_a_worker_that_never_read_what_it_was_sent_raises_nothing(spawned: list[subprocess.Popen]) -> None:
    procs = prestart.spawn(1)
    procs[0].kill()
    procs[0].wait()
    assert procs[0].stdin is not None
    procs[0].stdin.write('{"prepare": {}}\n')  # buffered here, never delivered: the process is gone
    prestart.release(procs)  # its pipe is broken: closing it is no error
    assert procs[0].stdin.closed
