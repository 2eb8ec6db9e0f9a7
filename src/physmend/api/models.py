"""Models handed to the API as objects: registered here under a name that ``model.builder`` can import.

``model.builder: physmend.api.models:<name>`` resolves through this module's ``__getattr__`` to a
builder that returns a fresh copy of the registered :class:`~physmend.modeling.Model` (or calls the
registered builder function), so a stage composed from Python builds it as it builds a model file.
A builder function defined in an importable file is named by its file instead
(:func:`physmend.api.inputs.builder_of`), which later ``physmend`` commands can import too.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from typing import Any

_REGISTRY: dict[str, Callable[..., Any]] = {}
_NAMES: dict[int, str] = {}
_KEEP: list[Any] = []  # the registered objects, alive so that their ids are never reused
_UNSAFE = re.compile(r"\W")


def register(model: Any) -> str:
    """The ``model.builder`` reference of ``model`` (a Model or a builder function)."""
    from physmend.api.inputs import builder_of
    from physmend.modeling import Model

    if not isinstance(model, Model):
        found = builder_of(model)
        if found is not None:
            return found
    key = id(model)
    if key not in _NAMES:
        label = model.name if isinstance(model, Model) else getattr(model, "__name__", "builder")
        name = f"m{len(_NAMES) + 1}_{_UNSAFE.sub('_', str(label))[:40]}"
        if isinstance(model, Model):
            frozen = copy.deepcopy(model)  # later edits of the caller's object do not change a run

            def build() -> Model:
                return copy.deepcopy(frozen)

            _REGISTRY[name] = build
        else:
            _REGISTRY[name] = model
        _NAMES[key] = name
        _KEEP.append(model)
    return f"{__name__}:{_NAMES[key]}"


def __getattr__(name: str) -> Callable[..., Any]:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise AttributeError(f"no model registered as {name!r} in this Python process (a model given as an "
                             "object lives as long as the process; name a model file for later commands)") from None
