"""Universal differential equations: the hybrid model, its training and its artifacts.

Imports go one way: a module imports only modules on its own line of this list or below it
(each module's docstring names what it imports):

* ``train`` (one model) and ``stack`` (a package: several as one batched solve) — the two trainers,
  siblings: neither imports the other; ``checkpoints`` (the rules both follow: best checkpoint,
  patience, restarts, polishing) and ``polish`` (L-BFGS after Adam);
* ``artifacts`` (plain files and figures of a trained model), ``io`` (reading them back),
  ``analysis`` and ``rates`` (what a trained model learned);
* ``warmstart`` (derivative matching), ``schedule`` (learning rate per epoch, cycles, patience), ``metrics``
  (whole-trajectory evaluation), ``outcome`` (``TrainResult``, ``TrainingDiverged``);
* ``spec`` (the hybrid's specification from ``cfg.ude``; settings come typed and checked from
  :mod:`physmend.settings`), ``shooting`` (the plan of segments, RK4);
* ``reference`` (the model as written, solver options, sample masks), ``timescale`` (``auto`` time
  settings), ``hybrid`` (the hybrid model itself).
"""

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
