"""Refrigerated two-zone cargo box: the engineer's model and its (synthetic) telemetry.

``build_model()`` returns the engineer's :class:`physmend.modeling.Model` (28 states after
simplification). The telemetry of three experiments lies in the ``telemetry/`` folder of this
package (``pkg://physmend.library.cargo_box/telemetry``); ``python -m
physmend.library.cargo_box.generate`` regenerates it. See ``README.md`` beside this file.
"""

from __future__ import annotations

from physmend.library.cargo_box.model import INPUTS, N_STATES, OUTPUTS, build_model

__all__ = ["INPUTS", "N_STATES", "OUTPUTS", "build_model"]
