"""Errors raised by the simulator."""

from __future__ import annotations

from physmend.exceptions import PhysmendError


class SimulationError(PhysmendError, RuntimeError):
    """Integration failed; the message names the experiment and the time (s)."""
