"""Universal differential equations: the hybrid model, its training and its artifacts."""

from __future__ import annotations

from physmend.ude.hybrid import HybridModel, HybridSpec, UDEConfigError
from physmend.ude.io import ArtifactError, load_hybrid
from physmend.ude.train import TrainingDiverged, TrainResult, evaluate, reference, train

__all__ = [
    "ArtifactError",
    "HybridModel",
    "HybridSpec",
    "TrainResult",
    "TrainingDiverged",
    "UDEConfigError",
    "evaluate",
    "load_hybrid",
    "reference",
    "train",
]
