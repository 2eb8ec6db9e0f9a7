"""Symbolic models: declaration, acausal components, structural simplification, torch compilation."""

from __future__ import annotations

from physmend.modeling.compile import CompiledModel, compile_model
from physmend.modeling.corrections import Correction, apply_corrections, read_corrections, write_corrections
from physmend.modeling.errors import ModelError
from physmend.modeling.loader import load_model
from physmend.modeling.model import Connector, Equation, Model, Output, Variable
from physmend.modeling.simplify import SimplifiedModel, simplify

__all__ = [
    "CompiledModel",
    "Correction",
    "apply_corrections",
    "read_corrections",
    "write_corrections",
    "Connector",
    "Equation",
    "Model",
    "ModelError",
    "Output",
    "SimplifiedModel",
    "Variable",
    "compile_model",
    "load_model",
    "simplify",
]
