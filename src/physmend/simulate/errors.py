"""Errors raised by the simulator."""

from __future__ import annotations


class SimulationError(RuntimeError):
    """Integration failed; the message names the experiment and the time (s)."""
