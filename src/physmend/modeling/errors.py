"""Errors raised while building, simplifying or compiling a model."""

from __future__ import annotations

from physmend.exceptions import PhysmendError


class ModelError(PhysmendError, ValueError):
    """A model is malformed or cannot be reduced to an explicit ODE; the message names the equations."""
