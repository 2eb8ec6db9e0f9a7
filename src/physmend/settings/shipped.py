"""What physmend ships: its directories (``conf``, ``sweeps``, ``examples``) and the defaults of its
configuration groups, read from ``conf/<group>/default.yaml`` (the one place every default lives)."""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any

import yaml

from physmend.exceptions import PhysmendError


class SettingError(PhysmendError, ValueError):
    """A setting has the wrong kind or range; the message names the key, the value and the rule."""


def shipped_dir(name: str) -> Path:
    """A directory physmend ships (``conf``, ``sweeps``, ``examples``): inside the installed package,
    or beside ``src/`` in a checkout."""
    here = Path(__file__).resolve().parents[1]
    for candidate in (here / name, here.parents[1] / name):
        if candidate.is_dir():
            return candidate
    raise SettingError(f"physmend's {name}/ directory is missing (looked in {here / name} and {here.parents[1] / name})")


@functools.lru_cache(maxsize=None)
def _shipped(group: str) -> dict[str, Any]:
    if not group:  # the top level: conf/config.yaml's own keys (seed, threads, device)
        top = yaml.safe_load((shipped_dir("conf") / "config.yaml").read_text()) or {}
        return {key: value for key, value in top.items() if key != "defaults"}
    return yaml.safe_load((shipped_dir("conf") / group / "default.yaml").read_text()) or {}


def shipped_group(group: str) -> dict[str, Any]:
    """The shipped defaults of ``group`` (``conf/<group>/default.yaml``; ``""``: the top-level keys of
    ``conf/config.yaml``), a copy."""
    return copy.deepcopy(_shipped(group))


def shipped_default(group: str, key: str) -> Any:
    """The shipped default of ``group.key`` (``key`` dotted for nested keys), from ``conf/<group>/default.yaml``."""
    node: Any = _shipped(group)
    for part in key.split("."):
        node = node[part]
    return node
