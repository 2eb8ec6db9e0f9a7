"""The CPUs this process may use: what ``auto`` means for every setting that runs work side by side
(``mask.workers``, ``discover.workers``, the symbolic searches). Imports nothing heavy."""

from __future__ import annotations

import os


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the system tells it, else the machine's), ≥ 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)
