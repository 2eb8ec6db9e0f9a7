"""physmend: find the physics a model is missing.

Public entry points live in subpackages: :mod:`physmend.modeling` (write and simplify models),
:mod:`physmend.data` (telemetry), :mod:`physmend.simulate` (batched simulation),
:mod:`physmend.stages` (the pipeline) and :mod:`physmend.tracking` (MLflow conventions).
"""

from __future__ import annotations

__version__ = "0.1.0"
