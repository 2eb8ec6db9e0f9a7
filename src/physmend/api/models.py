"""Models handed to the API as objects: registered here under a name that ``model.builder`` can import.

``model.builder: physmend.api.models:<name>`` resolves through this module's ``__getattr__`` to a
builder that returns a fresh copy of the registered :class:`~physmend.modeling.Model` (or calls the
registered builder function), so a stage composed from Python builds it as it builds a model file.
A builder function defined in an importable file is named by its file instead
(:func:`builder_of`), which later ``physmend`` commands can import too.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

_REGISTRY: dict[str, Callable[..., Any]] = {}
_NAMES: dict[int, str] = {}
_KEEP: list[Any] = []  # the registered objects, alive so that their ids are never reused
_UNSAFE = re.compile(r"\W")


def register(model: Any) -> str:
    """The ``model.builder`` reference of ``model`` (a Model or a builder function)."""
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


def builder_of(fn: Callable[..., Any]) -> str | None:
    """``path/file.py:name`` when ``fn`` is a module-level function of a file it can be imported from
    again (so a later ``physmend`` command can name it), else None."""
    import inspect
    import sys

    name = getattr(fn, "__name__", "")
    module = sys.modules.get(getattr(fn, "__module__", "") or "")
    if not name or module is None or module.__name__ == "__main__" or getattr(module, name, None) is not fn:
        return None
    try:
        path = inspect.getsourcefile(fn)
    except TypeError:
        return None
    return f"{Path(path).resolve()}:{name}" if path and Path(path).is_file() else None
