"""The base class of every error that means "your input is wrong" (the lowest layer: imports nothing).

Catch :class:`PhysmendError` to handle any of them; each subclass (``ConfigError``, ``DataError``,
``ModelError``, ``SimulationError`` …) names the file, key, column or equation and what was expected.
"""

from __future__ import annotations


class PhysmendError(Exception):
    """Bad input to physmend (a setting, a data file, a model, a run ID); the message says which and why."""
