"""Errors that mean "your input is wrong" (reported as one message, no traceback) — and only those."""

from __future__ import annotations

from physmend.config import ConfigError
from physmend.data import DataError
from physmend.modeling.errors import ModelError
from physmend.simulate.errors import SimulationError
from physmend.tracking.store import TrackingError
from physmend.ude.hybrid import UDEConfigError
from physmend.symbolic import SymbolicError
from physmend.explain.mechanisms import MechanismError
from physmend.ude.outcome import TrainingDiverged
from physmend.ude.io import ArtifactError
from physmend.sweep.run import NoTrialCompleted

USER_ERRORS: tuple[type[Exception], ...] = (
    ArtifactError, ConfigError, DataError, MechanismError, ModelError, NoTrialCompleted, SimulationError,
    SymbolicError, TrackingError, TrainingDiverged, UDEConfigError,
)
