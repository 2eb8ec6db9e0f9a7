"""Reusable model components beyond the acausal thermal library (:mod:`physmend.modeling.thermal`).

User projects — a model file, a config directory and a telemetry generator each — live in the
repository's ``examples/`` folder (shipped inside the package as ``physmend/examples``), not here.
"""

from __future__ import annotations
