"""A live line for a step with no natural count (one batched solve of every experiment): on a
terminal, once the step has taken ``after`` seconds, ``diagnose: simulating 3 experiments as
written … 12 s`` redrawn every second on stderr and wiped when the step ends. Steps that count
(trials, epochs, formulas) have tqdm bars instead. Nothing is written where stderr is not a
terminal (a log file gets no line per second).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO


@contextmanager
def activity(what: str, *, after: float = 2.0, stream: TextIO | None = None) -> Iterator[None]:
    """Show ``what … N s`` on ``stream`` (default stderr, a terminal only) while the block runs."""
    out = stream if stream is not None else sys.stderr
    if not getattr(out, "isatty", lambda: False)():
        yield
        return
    done = threading.Event()
    start = time.monotonic()
    shown = [0]

    def tick() -> None:
        if done.wait(after):
            return
        while not done.is_set():
            line = f"{what} … {time.monotonic() - start:.0f} s"
            out.write("\r" + line)
            out.flush()
            shown[0] = max(shown[0], len(line))
            done.wait(1.0)

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        if shown[0]:
            out.write("\r" + " " * shown[0] + "\r")
            out.flush()
