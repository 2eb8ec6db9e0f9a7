"""Symbolic models: declaration, acausal components, structural simplification, torch compilation.

The public names below are imported on first use (``from physmend.modeling import Model``), so
that importing a light submodule (``physmend.modeling.evaluate``) does not import torch.
Layer: imports nothing of physmend above ``physmend.config``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_HOMES = {
    "CompiledModel": "compile",
    "compile_model": "compile",
    "Correction": "corrections",
    "apply_corrections": "corrections",
    "read_corrections": "corrections",
    "write_corrections": "corrections",
    "ModelError": "errors",
    "load_model": "loader",
    "Connector": "model",
    "Model": "model",
    "Equation": "parts",
    "Output": "parts",
    "Variable": "parts",
    "SimplifiedModel": "simplify",
    "simplify": "simplify",
}

__all__ = sorted(_HOMES)

if TYPE_CHECKING:
    from physmend.modeling.compile import CompiledModel, compile_model
    from physmend.modeling.corrections import Correction, apply_corrections, read_corrections, write_corrections
    from physmend.modeling.errors import ModelError
    from physmend.modeling.loader import load_model
    from physmend.modeling.model import Connector, Model
    from physmend.modeling.parts import Equation, Output, Variable
    from physmend.modeling.simplify import SimplifiedModel, simplify


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'physmend.modeling' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"physmend.modeling.{home}"), name)
    globals()[name] = value
    return value
