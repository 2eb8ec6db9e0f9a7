"""Moved to :mod:`physmend.modeling.interval` (temporary alias while a benchmark run finishes)."""

from physmend.modeling.interval import *  # noqa: F401,F403
from physmend.modeling.interval import interval_violation, shift_violation  # noqa: F401
