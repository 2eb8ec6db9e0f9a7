"""Standby worker processes (:mod:`physmend.sweep.standby`): started, handed over, ended.

``physmend discover`` runs its sweep's first trials side by side where a second CPU is there
(``discover.workers: auto``). An extra worker spends seconds importing and compiling before it can
train, so discover starts it before its diagnose stage, and the command line starts the first one
even before it composes the configuration (:func:`start_early`): composing and the imports the
stages need take seconds of their own. This module imports the standard library only, so the
process starts at once. :func:`take` hands the early processes to the first caller that asks;
where the configuration asks for none (``discover.workers=1``, one trial), they are ended
(:func:`release`), having run nothing.
"""

from __future__ import annotations

import os
import subprocess
import sys

#: processes started before the configuration was composed, not yet taken
_EARLY: list[subprocess.Popen] = []


def spawn(count: int) -> list[subprocess.Popen]:
    """``count`` new standby processes (one thread each while they import and compile; the sweep that
    hands them their command line tells them their share of the CPUs)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return [subprocess.Popen([sys.executable, "-m", "physmend.sweep.standby"], env=env, stdin=subprocess.PIPE,
                             stdout=subprocess.DEVNULL, text=True) for _ in range(max(0, count))]


def start_early(count: int) -> None:
    """Start ``count`` standby processes now, for :func:`take` to hand over later."""
    _EARLY.extend(spawn(count))


def take(count: int) -> list[subprocess.Popen]:
    """Up to ``count`` of the early processes (oldest first); the others stay for :func:`release_early`."""
    taken = _EARLY[: max(0, count)]
    del _EARLY[: len(taken)]
    return taken


def release(procs: list[subprocess.Popen]) -> None:
    """End the standby processes never handed a command line (they have run nothing); those handed
    one are a sweep's workers, which the sweep waits for or ends itself."""
    for proc in procs:
        if proc.stdin is not None and not proc.stdin.closed:
            proc.kill()
            proc.wait()
            try:
                proc.stdin.close()
            except OSError:  # a brief it never read (physmend.sweep.standby.brief): nothing to deliver
                pass


def release_early() -> None:
    """End the early processes nobody took."""
    left = list(_EARLY)
    _EARLY.clear()
    release(left)
