"""The CPUs this process may use: what ``auto`` means for every setting that runs work side by side
(``mask.workers``, ``discover.workers``, the symbolic searches) and for ``threads``. Imports nothing heavy."""

from __future__ import annotations

import os


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the system tells it, else the machine's), ≥ 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


#: the environment variable that tells a process its share of the CPUs (OpenMP's own): a process
#: started to work beside others (a sweep's workers) is given it, and ``threads: auto`` obeys it
SHARE_ENV = "OMP_NUM_THREADS"


def threads(setting: int | str, side_by_side: int = 1) -> int:
    """The top-level ``threads`` setting as a count of threads for this process: a count as given;
    ``auto``: this process's share of the CPUs it may use when ``side_by_side`` processes (itself
    included) work at once — ``usable_cpus() // side_by_side`` — and at most ``OMP_NUM_THREADS`` where
    that is set to a whole number (a worker process is told its share that way; so is a test
    process). ≥ 1."""
    if str(setting) != "auto":
        return max(1, int(setting))
    share = max(1, usable_cpus() // max(1, int(side_by_side)))
    told = os.environ.get(SHARE_ENV, "").strip()
    if told.isdigit() and int(told) >= 1:
        share = min(share, int(told))
    return share
