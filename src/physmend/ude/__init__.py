"""Universal differential equations: the hybrid model, its training and its artifacts."""

from __future__ import annotations

from physmend.ude.hybrid import HybridModel, HybridSpec, UDEConfigError
from physmend.ude.io import ArtifactError, load_hybrid
from physmend.ude.metrics import evaluate
from physmend.ude.outcome import TrainResult, TrainingDiverged
from physmend.ude.reference import reference
from physmend.ude.train import train

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
