"""Credentials out of everything physmend logs, tags, saves or prints.

A tracking server or database URI may carry a password (``postgresql://user:secret@host/db``).
physmend passes such a URI to the library that opens the store, and nowhere else: every text that
leaves the process — a run's ``config.yaml``, its parameters and tags, an error line, ``physmend
config`` — goes through :func:`redact`, which keeps the user name and replaces the password by
``***``. :func:`printable` escapes terminal control characters in text read from a store. Imports
nothing of physmend.
"""

from __future__ import annotations

import re

#: ``scheme://user:password@`` (the user part may be empty); the password ends at the last ``@``
#: before the host, so passwords containing ``@``, ``:``, ``/`` or quotes are covered as well
_SECRET_IN_URI = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s:/@'\"]*):(?P<secret>\S*)@(?=[^\s@]*(?:\s|$))")
#: ``password=…`` in a query string or keyword list (``?password=…``, ``;Password=…``)
_SECRET_IN_QUERY = re.compile(r"(?P<head>(?:[?&;]|\b)(?:password|passwd|pwd|token|secret)=)(?P<secret>[^&;\s'\"]+)", re.IGNORECASE)

MASK = "***"


#: control characters (C0 but newline and tab, DEL, C1): a store's text could move the cursor, recolour or
#: retitle the user's terminal
_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def printable(text: str) -> str:
    """``text`` with every terminal control character written as an escape (``\\x1b``): what a store
    says is shown, never obeyed by the terminal."""
    return _CONTROL.sub(lambda m: repr(m.group(0))[1:-1], text)


def redact(text: str) -> str:
    """``text`` with the password of every URI in it (and ``password=`` query values) replaced by ``***``."""
    text = _SECRET_IN_URI.sub(lambda m: f"{m['head']}:{MASK}@", text)
    return _SECRET_IN_QUERY.sub(lambda m: f"{m['head']}{MASK}", text)
