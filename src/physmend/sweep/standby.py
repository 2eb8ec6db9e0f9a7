"""Worker processes started before their sweep: ``python -m physmend.sweep.standby`` imports what a
``physmend sweep`` worker needs (torch, Optuna, MLflow, sympy, physmend's training: seconds), then
waits for its command line on stdin — one line of JSON, ``{"argv": [...], "env": {...}}`` written
by the process that started it (:func:`physmend.sweep.workers._start_workers`) — and runs it as
``physmend`` would. Closed stdin without a line: it exits, having run nothing.

Before it, the process that started it may tell it the sweep it will join (:func:`brief`: a line
``{"prepare": {"overrides": [...], "config_dir": ...}}``). While it waits it then does what the
command does before it asks for its first trial, where this process keeps it (:func:`_prepare`):
the stores' modules imported (:func:`physmend.tracking.store.preload`; no store is opened), the
configuration composed and the model built and compiled (:func:`physmend.problem.load_problem`).
The cargo box's worker asked for its first trial ~8 s after the sweep started it where it did
all this then, and two workers meant to start their first trials together ran them one after the
other. Only what comes before that ask is prepared: work of the trial itself (the warm start's
smoothing, say) done here would delay the ask where the command line comes early. Nothing it
prepares changes a result; a failure in it is only time lost (the command does the same and
reports).

``physmend discover`` starts its sweep's extra workers this way before its diagnose stage, so that
they train from the moment the sweep asks for them instead of importing first (about 5 s of a
worker's start on 2 cores; 12 s where nothing is byte-compiled yet), and compile the training
solve's loops if nothing has yet (12–17 s, once per installation) before its other imports, so
that the main process finds them in numba's cache when its sweep starts
(:mod:`physmend.ude.compile_lock`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Any


def start(count: int) -> list[subprocess.Popen]:
    """``count`` standby processes importing while this process goes on: those the command line
    started before composing the configuration first (:func:`physmend.prestart.start_early`), new
    ones for the rest; early ones beyond ``count`` are ended."""
    from physmend import prestart

    ready = prestart.take(count)
    prestart.release_early()
    return ready + prestart.spawn(count - len(ready))


def hand(proc: subprocess.Popen, argv: list[str], env: dict[str, str]) -> subprocess.Popen | None:
    """Give standby process ``proc`` its command line (``physmend`` arguments) and environment;
    None when it can no longer take one (it ended: the caller starts a new process instead)."""
    if proc.stdin is None or proc.stdin.closed or proc.poll() is not None:
        return None
    try:
        proc.stdin.write(json.dumps({"argv": argv, "env": env}) + "\n")
        proc.stdin.close()
    except OSError:
        return None
    return proc


def brief(procs: list[subprocess.Popen], overrides: list[str], config_dir: str | None) -> None:
    """Tell standby processes ``procs`` the sweep worker's overrides and config folder they will be
    handed (:func:`physmend.sweep.workers.worker_overrides`), for them to prepare while they wait;
    one that can no longer listen is skipped (it will not be handed a command line either)."""
    line = json.dumps({"prepare": {"overrides": [str(o) for o in overrides],
                                   "config_dir": None if config_dir is None else str(config_dir)}}) + "\n"
    for proc in procs:
        if proc.stdin is None or proc.stdin.closed or proc.poll() is not None:
            continue
        try:
            proc.stdin.write(line)
            proc.stdin.flush()
        except OSError:
            continue


def release(procs: list[subprocess.Popen]) -> None:
    """End the standby processes never handed a command line (they have run nothing); those handed
    one are the sweep's workers, which the sweep waits for or ends itself."""
    from physmend import prestart

    prestart.release(procs)


def _serve() -> int:
    try:
        return _wait_and_run()
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the sweep reports it
        return 130


#: what a sweep worker imports, imported while waiting
PRELOAD = ("physmend.cli", "physmend.api.functions", "physmend.stages.sweep", "physmend.problem", "physmend.ude",
           "physmend.tracking")


def _wait_and_run() -> int:
    import importlib

    from physmend.ude.adjoint import warm

    # the training loops first (seconds, once per installation; then read from numba's cache): the
    # process that started this one waits for them when its sweep starts, and reads the cache then
    warm()
    for name in PRELOAD:
        importlib.import_module(name)
    while True:
        line = sys.stdin.readline()
        if not line.strip():
            return 0  # released unused
        order: dict[str, Any] = json.loads(line)
        if "prepare" not in order:
            break
        _prepare(order["prepare"])
    os.environ.update({str(k): str(v) for k, v in order.get("env", {}).items()})
    sys.argv = ["physmend", *(str(a) for a in order["argv"])]
    import runpy
    import warnings

    with warnings.catch_warnings():  # runpy's note that PRELOAD imported the module already: not the user's concern
        warnings.filterwarnings("ignore", message=r"'physmend\.cli' found in sys\.modules", category=RuntimeWarning)
        runpy.run_module("physmend.cli", run_name="__main__")  # `physmend <argv>`: exits with its status
    return 0


def _prepare(sweep: dict[str, Any]) -> None:
    """What the command of the sweep ``sweep`` (:func:`brief`'s message) does before it asks for its
    first trial, done now and kept in this process (see the module docstring)."""
    try:
        from physmend.config import compose
        from physmend.cpus import side_by_side
        from physmend.problem import load_problem
        from physmend.tracking.store import preload

        preload()
        cfg = compose([str(o) for o in sweep.get("overrides") or []], user_config_dir=sweep.get("config_dir"))
        with side_by_side(1):  # as the command loads it (sweep.workers=1 in a worker's overrides)
            load_problem(cfg)
    except Exception:  # noqa: BLE001 - only time is lost: the command does the same and reports what fails
        return


if __name__ == "__main__":
    raise SystemExit(_serve())
