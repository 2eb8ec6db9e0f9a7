"""The live line of a step with no count (:mod:`physmend.stages.activity`): on a real terminal (a
pseudo-terminal here) it appears once the step has taken a while, counts seconds and is wiped at
the end; written to a file (a log) it writes nothing."""

from __future__ import annotations

import os
import select
import time
from pathlib import Path

from physmend.stages.activity import activity


def _read_all(fd: int, quiet: float = 1.0) -> str:
    """Everything written to the pseudo-terminal ``fd``'s other end: a pty hands bytes over through
    the kernel's line discipline, a moment later under load, so one read may see only part."""
    data = b""
    while select.select([fd], [], [], quiet)[0]:
        data += os.read(fd, 4096)
    return data.decode()


def test_a_slow_step_shows_its_elapsed_time_on_a_terminal_and_nothing_in_a_log(tmp_path: Path) -> None:
    master, slave = os.openpty()
    with os.fdopen(slave, "w") as tty:
        with activity("diagnose: simulating 3 experiments as written", after=0.2, stream=tty):
            time.sleep(1.4)
        seen = _read_all(master)
    os.close(master)
    assert "\rdiagnose: simulating 3 experiments as written … 0 s" in seen and "… 1 s" in seen
    assert seen.endswith("\r")  # the line is wiped: what the stage prints next starts clean
    with open(tmp_path / "log.txt", "w") as log:
        with activity("diagnose: simulating", after=0.0, stream=log):
            time.sleep(0.2)
    assert (tmp_path / "log.txt").read_text() == ""
