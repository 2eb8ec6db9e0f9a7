"""A server child that stops with its parent: ``physmend ui`` runs ``mlflow ui`` through this.

``mlflow ui`` is a launcher: it starts the web server (uvicorn) as its own child and waits. Ctrl-C in
a terminal reaches every process of the foreground group, but a SIGTERM (``kill PID``, a service
manager, a container stopping) or a SIGHUP (the terminal closed) reaches only the process it is sent
to: the launcher died and the web server went on holding the port. So the child runs in a process
group of its own, and each of SIGTERM, SIGHUP and SIGINT received by physmend is passed to that
whole group; physmend returns once every process of the group has ended (those still running
:data:`GRACE_S` seconds later are killed). Elsewhere than POSIX the child alone is terminated.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import FrameType

#: seconds the server's processes get to stop after a signal before they are killed
GRACE_S = 10.0
#: the signals that stop the server with physmend (those this platform has)
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, name))


def run_server(cmd: Sequence[str], env: Mapping[str, str]) -> int:
    """Run ``cmd`` until it exits or physmend is told to stop; return its exit status, or
    ``128 + signal`` when a signal stopped it (130 for Ctrl-C, 143 for SIGTERM)."""
    posix = os.name == "posix"
    received: list[int] = []
    proc: subprocess.Popen[bytes] | None = None

    def stop(signum: int, _frame: FrameType | None) -> None:
        received.append(signum)
        if proc is not None:
            _signal_group(proc, signal.SIGTERM if signum != signal.SIGINT else signal.SIGINT, posix)

    main = threading.current_thread() is threading.main_thread()  # only it may set signal handlers
    previous = {s: signal.signal(s, stop) for s in STOP_SIGNALS} if main else {}
    try:
        proc = subprocess.Popen(list(cmd), env=dict(env), start_new_session=posix)
        if received:  # a signal came while it was starting
            _signal_group(proc, signal.SIGTERM, posix)
        status = proc.wait()
        if posix:  # the launcher has ended; its web server may still be stopping
            _end_group(proc.pid)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    if received:
        print(f"physmend ui: stopped by {signal.Signals(received[0]).name}; the MLflow server is stopped too",
              file=sys.stderr)
        return 128 + received[0]
    return status


def _signal_group(proc: subprocess.Popen[bytes], signum: int, posix: bool) -> None:
    try:
        if posix:
            os.killpg(proc.pid, signum)
        else:
            proc.terminate()
    except (ProcessLookupError, PermissionError):
        pass


def _end_group(pgid: int) -> None:
    """Wait up to :data:`GRACE_S` seconds for the processes of group ``pgid`` to end, then kill the rest."""
    deadline = time.monotonic() + GRACE_S
    while _group_alive(pgid):
        if time.monotonic() > deadline:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            return
        time.sleep(0.1)


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` still runs (one that ended but was not yet reaped by its
    new parent does not count: it holds no port)."""
    proc = Path("/proc")
    if not proc.is_dir():
        try:
            os.killpg(pgid, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # ended meanwhile
        if int(fields[2]) == pgid and fields[0] != "Z":  # state, ppid, pgrp …
            return True
    return False
