"""A Ctrl-C that Python dropped, raised again.

Python raises ``KeyboardInterrupt`` wherever the main thread is when SIGINT arrives. Where that is an
object's finaliser (``__del__``, a weakref callback: GitPython's, sqlite's, any library's, run by
a garbage collection in the middle of a trial) Python prints "Exception ignored in …" and drops it,
and the sweep went on as if no key was pressed. Within :func:`kept`, SIGINT raises as Python's own
handler does and is also remembered; :func:`check` raises it again where the sweep can act on it (at
each epoch's report, before each trial). The first ``KeyboardInterrupt`` that is not dropped ends
the sweep, so one raised again is never a second one.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

#: whether SIGINT arrived within :func:`kept` (this process)
_PENDING = {"sigint": False}


@contextmanager
def kept() -> Iterator[None]:
    """Within: SIGINT raises ``KeyboardInterrupt`` and is remembered for :func:`check`. Only where
    Python's own handler is in place on the main thread (a notebook's or a caller's own handler is
    left alone); the handler before is restored after."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def remember(signum: int, frame: FrameType | None) -> None:
        _PENDING["sigint"] = True
        raise KeyboardInterrupt

    _PENDING["sigint"] = False
    previous = signal.signal(signal.SIGINT, remember)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _PENDING["sigint"] = False


def check() -> None:
    """Raise ``KeyboardInterrupt`` if SIGINT arrived within :func:`kept` (a no-op otherwise)."""
    if _PENDING["sigint"]:
        raise KeyboardInterrupt("Ctrl-C (raised again: Python had dropped it in a finaliser)")
