"""Rebuilding a trained hybrid model from its plain-file artifacts (written by
:func:`physmend.ude.artifacts.artifacts_of`). Imports ``hybrid``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from physmend.problem import Problem
from physmend.ude.hybrid import HybridModel, HybridSpec


class ArtifactError(ValueError):
    """A run's model artifacts are missing or do not fit the model; the message names the file."""


def load_hybrid(cfg: Any, problem: Problem, artifact_dir: Path) -> HybridModel:
    """Rebuild the hybrid model saved under ``artifact_dir/model/`` (``hybrid.json`` + ``weights.pt``)."""
    folder = Path(artifact_dir) / "model"
    meta_path, weights_path = folder / "hybrid.json", folder / "weights.pt"
    for path in (meta_path, weights_path):
        if not path.is_file():
            raise ArtifactError(f"model artifact {str(path)!r} is missing; was this run written by a physmend trial?")
    meta = json.loads(meta_path.read_text())
    spec = HybridSpec(**meta["spec"])
    missing = [n for n in spec.corrected + spec.in_states if n not in problem.model.state_names]
    if missing:
        raise ArtifactError(f"{meta_path}: the model has no states {missing}; the run was trained on another model")
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    state = torch.load(weights_path, weights_only=True)
    hybrid.load_state_dict({k: v.to(problem.dtype) if v.is_floating_point() else v for k, v in state.items()})
    hybrid.eval()
    return hybrid
