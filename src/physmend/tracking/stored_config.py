"""A run's ``config.yaml`` read as data, not as instructions.

A store is shared: whatever a run's artifacts say was written by someone else. So a stored
configuration is never *resolved* (an interpolation such as ``${oc.env:HOME}`` is refused, not
evaluated), and the model is never built from the builder a stored configuration names: the
current user's own ``model`` and ``data`` configuration is used, after checking that the run was
made with the same ones (a run made with another model or data is one clear error naming the run
and the first difference).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.tracking.store import TrackingError

TRUSTED_GROUPS = ("model", "data")


def _interpolation(node: Any, prefix: str = "") -> tuple[str, str] | None:
    if isinstance(node, dict):
        for k, v in node.items():
            found = _interpolation(v, f"{prefix}{k}.")
            if found:
                return found
    elif isinstance(node, list):
        for i, v in enumerate(node):
            found = _interpolation(v, f"{prefix}{i}.")
            if found:
                return found
    elif isinstance(node, str) and "${" in node:
        return prefix.rstrip("."), node
    return None


def _first_difference(a: Any, b: Any, prefix: str) -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            found = _first_difference(a.get(k), b.get(k), f"{prefix}.{k}")
            if found:
                return found
        return None
    return None if a == b else f"{prefix}: the run has {_short(a)}, your configuration {_short(b)}"


def _short(value: Any, limit: int = 100) -> str:
    """``repr(value)`` cut to about ``limit`` characters, its start and end kept (an error never echoes
    a whole file; the end of a path names its file)."""
    text = repr(value)
    if len(text) <= limit:
        return text
    return f"{text[:limit * 2 // 3]}…{text[-(limit // 3):]} ({len(text)} characters)"


def read_stored_config(path: str | Path, run_id: str, current: DictConfig | None = None) -> DictConfig:
    """The configuration stored at ``path`` by run ``run_id``, as data.

    With ``current`` (the user's composed configuration), its ``model`` and ``data`` groups must
    equal the run's (``model.corrections`` aside) and replace them, so nothing the store names is
    imported. Without it (a call from Python), the stored groups are kept: the caller trusts the store.

    Raises:
        TrackingError: the file holds an interpolation, or the run was made with another model or data.
    """
    from physmend.modeling.safe_yaml import load_bounded

    raw = load_bounded(path, TrackingError, where=f"run {run_id!r}: config.yaml")
    if not isinstance(raw, dict):
        raise TrackingError(f"run {run_id!r}: config.yaml must hold a mapping, but holds {type(raw).__name__}")
    found = _interpolation(raw)
    if found:
        raise TrackingError(
            f"run {run_id!r}: config.yaml holds an interpolation at {found[0][:100]} ({_short(found[1])}); a stored "
            "configuration is data and is never resolved"
        )
    if current is not None:
        for group in TRUSTED_GROUPS:
            mine = OmegaConf.to_container(current[group], resolve=True) if group in current else None
            theirs = raw.get(group)
            if group == "model" and isinstance(mine, dict) and isinstance(theirs, dict):
                mine = {k: v for k, v in mine.items() if k != "corrections"}
                theirs = {k: v for k, v in theirs.items() if k != "corrections"}
            diff = _first_difference(theirs, mine, group)
            if diff:
                raise TrackingError(
                    f"run {run_id!r} was made with another {group} configuration ({diff}): pass the same "
                    f"{group}=… (and --config-dir) as for that run; physmend builds the model only from your "
                    "own configuration, never from what a store names"
                )
            raw[group] = OmegaConf.to_container(current[group], resolve=True)
    cfg = OmegaConf.create(raw)
    assert isinstance(cfg, DictConfig)
    return cfg
