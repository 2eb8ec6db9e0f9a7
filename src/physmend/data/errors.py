"""Errors raised while reading a data config or telemetry files."""

from __future__ import annotations

from physmend.exceptions import PhysmendError


class DataError(PhysmendError, ValueError):
    """A data config or telemetry file is malformed.

    The message names the file (or config key), the offending column or key, the rule that was
    broken and the actual value found.
    """
