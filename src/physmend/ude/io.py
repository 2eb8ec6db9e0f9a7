"""Rebuilding a trained hybrid model from its plain-file artifacts (written by
:func:`physmend.ude.artifacts.artifacts_of`), checked as data first (:mod:`physmend.ude.stored_spec`).
Imports ``hybrid``, ``stored_spec``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from physmend.problem import Problem
from physmend.ude.hybrid import HybridModel
from physmend.ude.stored_spec import SPEC_FILE, WEIGHTS_FILE, ArtifactError, read_spec, read_weights

__all__ = ["ArtifactError", "load_hybrid"]


def load_hybrid(cfg: Any, problem: Problem, artifact_dir: Path) -> HybridModel:
    """Rebuild the hybrid model saved under ``artifact_dir/model/`` (``hybrid.json`` + ``weights.pt``).

    Raises:
        ArtifactError: a file is missing, or does not describe a network of ``problem``'s model
            within the configuration's bounds (one line naming the file and key).
    """
    folder = Path(artifact_dir)
    for rel in (SPEC_FILE, WEIGHTS_FILE):
        if not (folder / rel).is_file():
            raise ArtifactError(f"model artifact {rel!r} is missing; was this run written by a physmend trial?")
    spec = read_spec(folder / SPEC_FILE, problem)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    state = read_weights(folder / WEIGHTS_FILE, hybrid.state_dict())
    hybrid.load_state_dict({k: v.to(problem.dtype) if v.is_floating_point() else v for k, v in state.items()})
    hybrid.eval()
    return hybrid
