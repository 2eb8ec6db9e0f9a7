"""Credentials out of everything physmend logs, tags, saves or prints.

A tracking server or database URI may carry a password (``postgresql://user:secret@host/db``).
physmend passes such a URI to the library that opens the store, and nowhere else: every text that
leaves the process — a run's ``config.yaml``, its parameters and tags, an error line, ``physmend
config`` — goes through :func:`redact`, which keeps the user name and replaces the password by
``***``. Imports nothing of physmend.
"""

from __future__ import annotations

import re

#: ``scheme://user:password@`` (the user part may be empty); the password ends at the last ``@``
#: before the host, so passwords containing ``@``, ``:`` or ``/`` are covered as well
_SECRET_IN_URI = re.compile(r"(?P<head>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s:/@'\"]*):(?P<secret>[^\s'\"]*)@(?=[^\s@'\"]*(?:[\s'\"]|$))")
#: ``password=…`` in a query string or keyword list (``?password=…``, ``;Password=…``)
_SECRET_IN_QUERY = re.compile(r"(?P<head>(?:[?&;]|\b)(?:password|passwd|pwd|token|secret)=)(?P<secret>[^&;\s'\"]+)", re.IGNORECASE)

MASK = "***"


def redact(text: str) -> str:
    """``text`` with the password of every URI in it (and ``password=`` query values) replaced by ``***``."""
    text = _SECRET_IN_URI.sub(lambda m: f"{m['head']}:{MASK}@", text)
    return _SECRET_IN_QUERY.sub(lambda m: f"{m['head']}{MASK}", text)
