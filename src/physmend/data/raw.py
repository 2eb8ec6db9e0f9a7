"""A data config's raw values: plain containers from OmegaConf ones, misspelt keys caught with a
close match named, finite numbers."""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from typing import Any

from physmend.data.errors import DataError


def _close(word: str, options: Sequence[str], n: int = 3, cutoff: float = 0.6) -> list[str]:
    return difflib.get_close_matches(word, list(options), n=n, cutoff=cutoff)


def _did_you_mean(word: str, options: Sequence[str]) -> str:
    matches = _close(word, options)
    return f"; close matches: {matches}" if matches else ""


def to_plain(data_cfg: Any) -> Any:
    """An OmegaConf container (resolved) or any mapping/sequence as plain ``dict``/``list``."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        DictConfig = ListConfig = ()  # type: ignore[assignment,misc]
    if DictConfig and isinstance(data_cfg, (DictConfig, ListConfig)):
        try:
            return OmegaConf.to_container(data_cfg, resolve=True)
        except Exception as exc:  # interpolation errors and the like
            raise DataError(f"data config cannot be resolved: {exc}") from exc
    if isinstance(data_cfg, Mapping):
        return {k: to_plain(v) for k, v in data_cfg.items()}
    if isinstance(data_cfg, (list, tuple)):
        return [to_plain(v) for v in data_cfg]
    return data_cfg


def _check_typos(mapping: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    """Unknown keys are allowed (extensions), unless one looks like a misspelt known key."""
    for key in mapping:
        if key in known or not isinstance(key, str):
            continue
        matches = _close(key, known, n=1, cutoff=0.75)
        if matches:
            raise DataError(
                f"{where}: unknown key {key!r}; did you mean {matches[0]!r}? "
                f"(known keys: {list(known)})"
            )


def _number(value: Any, what: str) -> float:
    """``value`` as a finite float, else a DataError naming ``what``."""
    if isinstance(value, bool):
        raise DataError(f"{what} must be a finite number, but got {value!r}")
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise DataError(f"{what} must be a finite number, but got {value!r}") from None
    if not math.isfinite(out):
        raise DataError(f"{what} must be a finite number, but got {value!r}")
    return out
