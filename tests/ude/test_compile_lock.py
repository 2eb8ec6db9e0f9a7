"""The training loops' compile lock: a second process waits for the first, and never without bound."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from physmend.ude.compile_lock import compiling, lock_path

pytest.importorskip("fcntl")

HOLD = """
import sys, time
from physmend.ude.compile_lock import compiling
with compiling(sys.argv[1]) as held:
    print("held" if held else "free", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _holder(module_file: str, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLD, module_file, str(seconds)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_process_waits_for_the_first_to_finish_compiling(tmp_path):
    module = str(tmp_path / "loops.py")
    proc = _holder(module, 1.5)
    start = time.monotonic()
    with compiling(module) as held:
        waited = time.monotonic() - start
        assert held
    assert waited >= 1.0  # the holder kept it 1.5 s after saying so
    proc.wait()


def test_the_wait_is_bounded_and_the_block_runs_anyway(tmp_path):
    module = str(tmp_path / "loops.py")
    proc = _holder(module, 30)
    try:
        start = time.monotonic()
        with compiling(module, wait_s=0.3) as held:
            assert not held
        assert 0.3 <= time.monotonic() - start < 5
    finally:
        proc.kill()
        proc.wait()


def test_a_holder_that_dies_releases_the_lock(tmp_path):
    module = str(tmp_path / "loops.py")
    proc = _holder(module, 30)
    proc.kill()
    proc.wait()
    start = time.monotonic()
    with compiling(module, wait_s=10) as held:
        assert held
    assert time.monotonic() - start < 2


def test_two_installations_have_two_locks_and_a_planted_link_is_not_followed(tmp_path):
    first, second = str(tmp_path / "a" / "loops.py"), str(tmp_path / "b" / "loops.py")
    assert lock_path(first) != lock_path(second)
    target = tmp_path / "victim.txt"
    target.write_text("the user's file")
    module = str(tmp_path / "c" / "loops.py")
    path = lock_path(module)
    if os.path.lexists(path):
        os.remove(path)
    os.symlink(target, path)
    try:
        with compiling(module, wait_s=0.1) as held:
            assert not held  # O_NOFOLLOW: the link is refused, nothing waits, the block runs
        assert target.read_text() == "the user's file"
    finally:
        os.remove(path)
