"""Ready-made models with their telemetry generators.

* :mod:`physmend.library.cargo_box` — a refrigerated two-zone cargo box (the seed paper's
  example): the engineer's model (``build_model``) and synthetic telemetry of three experiments
  recorded from a box with physics the model leaves out.

Subpackages are imported on demand (``import physmend.library.cargo_box``), not here.
"""

from __future__ import annotations
