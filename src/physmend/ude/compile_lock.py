"""One process at a time compiles the training loops; the others then read numba's cache.

The loops of :mod:`physmend.ude.rk4_loops` are compiled once per installation and cached beside
the module (numba's ``cache=True``). ``physmend discover`` has two processes that want them at
about the same time on a fresh install: the sweep's standby worker, which compiles them while the
diagnose stage runs, and the main process, when its sweep starts. Without coordination both
compile (15–20 s of CPU each on 2 cores, the second contending with the first); with this lock the
second waits for the first and then reads the cache (about 1.5 s).

The lock is an advisory ``flock`` on a file in the temporary folder, named after the loops' module
path (two installations do not wait for each other). The operating system releases it when its
holder ends, however it ends. Where locking is not possible (no ``fcntl``, the file cannot be
opened) nothing waits, and at most :data:`WAIT_S` seconds are waited before compiling anyway: a
stuck holder costs time, never a hang.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
from collections.abc import Iterator

WAIT_S = 120.0
"""Seconds at most to wait for another process's compilation before compiling here as well."""


def lock_path(module_file: str) -> str:
    """The lock file for the loops compiled from ``module_file`` (a path): in the temporary folder,
    named after a hash of the path and the user ID."""
    uid = getattr(os, "getuid", lambda: 0)()
    key = hashlib.sha256(f"{os.path.abspath(module_file)}|{uid}".encode()).hexdigest()[:16]
    return os.path.join(tempfile.gettempdir(), f"physmend-loops-{key}.lock")


@contextlib.contextmanager
def compiling(module_file: str, wait_s: float = WAIT_S) -> Iterator[bool]:
    """Hold the compile lock of ``module_file``'s loops while the block runs; yields whether this
    process holds it (False: no lock was possible, or ``wait_s`` seconds passed: the block runs anyway)."""
    try:
        import fcntl
    except ImportError:  # not POSIX
        yield False
        return
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(lock_path(module_file), flags, 0o600)
    except OSError:
        yield False
        return
    held = False
    try:
        deadline = time.monotonic() + max(0.0, wait_s)
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                held = True
                break
            except OSError:
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.1)
        yield held
    finally:
        if held:
            fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
