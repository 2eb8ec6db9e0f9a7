"""Errors raised by symbolic regression."""

from __future__ import annotations

from physmend.exceptions import PhysmendError


class SymbolicError(PhysmendError, ValueError):
    """Bad input to symbolic regression, an unknown back end or option, or a bad Pareto choice.

    The message states the rule that was broken and the actual value found.
    """


class BackendUnavailable(SymbolicError):
    """The requested back end cannot run on this machine (a package or Julia is missing).

    Raised before anything slow is attempted: nothing is imported, installed or downloaded.
    """
