"""Worker processes, identity, heartbeats and stale trials: what a worker records on its running
trial, and when another worker may mark that trial FAIL (interrupted).

Identity
    Each worker process draws a random ID once (``uuid4``) and records it on every trial it runs,
    with its host name, PID and *process namespace* (the kernel's boot ID and the PID namespace:
    two containers on one host, or two machines, never share it). A RUNNING trial is stale when

    * its worker ID is this process's own (a worker about to ask for a trial runs none), or
    * its worker shares this process's namespace and its PID no longer exists, or
    * its last heartbeat is older than ``sweep.stale_after`` seconds (any worker, any machine).

    Host names and PIDs alone are not trusted: containers on different machines may share both.
    Trials recorded by older versions (host and PID, no ID) are judged as before: same host and a
    dead or equal PID.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from physmend.sweep.storage import HEARTBEAT_ATTR, WORKER_ATTR

if TYPE_CHECKING:
    import optuna


WORKER_ID = uuid.uuid4().hex
"""This process's worker ID: random, drawn once per process (a started worker is a new process)."""


def _namespace() -> str:
    """``<boot id>:<PID namespace>`` of this process; ``""`` where the system does not tell."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        pidns = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return ""
    return f"{boot}:{pidns}"


def this_worker() -> dict[str, Any]:
    """What a worker records on its running trial (see the module docstring)."""
    return {"id": WORKER_ID, "host": socket.gethostname(), "pid": os.getpid(), "ns": _namespace()}


def _pid_alive(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError, TypeError, OverflowError):
        return True  # exists but not ours, or unknown: let the heartbeat decide
    return True


def is_stale(trial: Any, *, now: float, stale_after: float, me: dict[str, Any]) -> bool:
    """Whether a RUNNING trial's worker is gone (see the module docstring)."""
    worker = trial.user_attrs.get(WORKER_ATTR) or {}
    if worker.get("id") is not None:
        if worker["id"] == me.get("id"):
            return True  # this process runs no trial while it looks
        if worker.get("ns") and worker.get("ns") == me.get("ns") and not _pid_alive(worker.get("pid")):
            return True  # same machine and PID namespace, and that process is gone
    elif worker.get("host") == me["host"]:  # recorded by an older version: host and PID only
        if worker.get("pid") == me["pid"] or not _pid_alive(worker.get("pid")):
            return True  # this process runs no trial while it looks; a dead PID runs none either
    beat = trial.user_attrs.get(HEARTBEAT_ATTR)
    if beat is None and trial.datetime_start is not None:
        beat = trial.datetime_start.timestamp()
    return beat is not None and now - float(beat) > stale_after



class Heartbeat:
    """Context manager: record ``time.time()`` on a trial every ``interval`` s from a thread."""

    def __init__(self, trial: "optuna.Trial", interval: float) -> None:
        self.trial, self.interval = trial, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="physmend-heartbeat", daemon=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.trial.set_user_attr(HEARTBEAT_ATTR, time.time())
            except Exception:  # noqa: BLE001 - a missed beat is harmless; the next one retries
                pass

    def __enter__(self) -> Heartbeat:
        self.trial.set_user_attr(HEARTBEAT_ATTR, time.time())
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


GIVEN_WINS_ENV = "PHYSMEND_SWEEP_GIVEN_WINS"
"""Set to ``1`` in the environment of the worker processes of a sweep whose command-line keys win
over its search space (``physmend discover``): they leave the same keys out of the search."""


PROBED_ENV = "PHYSMEND_SWEEP_PROBED"
"""Set to ``1`` in the environment of the worker processes a sweep starts: the sweep has composed
every choice of its space with its command line already (``probe_space``), so they do not again."""


def worker_overrides(overrides: Sequence[str]) -> list[str]:
    """The overrides a sweep's extra worker process is started with, given the sweep's own."""
    return [*overrides, "sweep.workers=1", "sweep.progress=false"]


def _start_workers(count: int, source_run_id: str | None, overrides: Sequence[str], config_dir: str | Path | None,
                   given_wins: bool = False, standby: Sequence[Any] = ()) -> list[Any]:
    """``count`` more ``physmend sweep`` processes on the same study (each told its share of the CPUs), started
    once this one has checked everything it was given: the ``standby`` processes first
    (:mod:`physmend.sweep.standby`, already importing), new ones for the rest."""
    if count < 1:
        return []
    args = ["sweep", *([source_run_id] if source_run_id else []),
            *(["--config-dir", str(config_dir)] if config_dir is not None else []), *worker_overrides(overrides)]
    from physmend.cpus import threads
    from physmend.sweep import standby as waiting

    share = str(threads("auto", count + 1))  # each process's share of the CPUs (threads: auto obeys it)
    ours = {"OMP_NUM_THREADS": share, "MKL_NUM_THREADS": share, GIVEN_WINS_ENV: "1" if given_wins else "0", PROBED_ENV: "1"}

    ready: list[Any] = []
    for proc in standby:
        if len(ready) < count and waiting.hand(proc, args, ours) is not None:
            ready.append(proc)
    env = {**os.environ, **ours}
    return ready + [subprocess.Popen([sys.executable, "-m", "physmend.cli", *args], env=env, stdout=subprocess.DEVNULL)
                    for _ in range(count - len(ready))]


def _join_workers(helpers: list[Any]) -> None:
    """Wait for the worker processes; say which ended with an error (their stderr is the user's)."""
    for proc in helpers:
        rc = proc.wait()
        if rc != 0:
            sys.stderr.write(f"sweep worker process {proc.pid} ended with exit status {rc}\n")
