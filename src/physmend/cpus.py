"""The CPUs this process may use: what ``auto`` means for every setting that runs work side by side
(``mask.workers``, ``discover.workers``, the symbolic searches) and for ``threads``. Imports nothing heavy."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the system tells it, else the machine's), ≥ 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


#: the environment variable that tells a process its share of the CPUs (OpenMP's own): a process
#: started to work beside others (a sweep's workers) is given it, and ``threads: auto`` obeys it
SHARE_ENV = "OMP_NUM_THREADS"


#: processes working at once, this one included, while :func:`side_by_side` holds (1: alone)
_AT_ONCE = [1]


@contextmanager
def side_by_side(processes: int) -> Iterator[None]:
    """Within: this process is one of ``processes`` working at once (a sweep's workers, or the ones
    waiting to become them), so ``threads: auto`` is its share of the CPUs — also where a stage
    loads a problem again (a trial's configuration) in the meantime."""
    _AT_ONCE.append(max(1, int(processes)))
    try:
        yield
    finally:
        _AT_ONCE.pop()


def threads(setting: int | str, side_by_side: int | None = None) -> int:
    """The top-level ``threads`` setting as a count of threads for this process: a count as given;
    ``auto``: this process's share of the CPUs it may use when ``side_by_side`` processes (itself
    included; default: as :func:`side_by_side` says, else 1) work at once — ``usable_cpus() //
    side_by_side`` — and at most ``OMP_NUM_THREADS`` where that is set to a whole number (a worker
    process is told its share that way; so is a test process). ≥ 1."""
    if str(setting) != "auto":
        return max(1, int(setting))
    at_once = _AT_ONCE[-1] if side_by_side is None else side_by_side
    share = max(1, usable_cpus() // max(1, int(at_once)))
    told = os.environ.get(SHARE_ENV, "").strip()
    if told.isdigit() and int(told) >= 1:
        share = min(share, int(told))
    return share
