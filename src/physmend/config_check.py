"""Settings checked when the configuration is composed, before any run or file is written.

The groups training reads (``train``, ``ude``, ``simulate``) are typed: each key's rule is a field
of its settings class (:data:`physmend.settings.TYPED`). Every setting of the other shipped groups
(``sweep``, ``symbolic`` …) keeps the kind of its shipped default: a whole number stays a whole
number ≥ 0, a number a finite number (> 0 where the default is positive, ≥ 0 where it is zero), a
switch ``true``/``false``, a word a word (and, for the keys in :data:`CHOICES`, one of the listed
words); a default ``auto`` accepts ``auto`` or a number > 0. :data:`RANGES` adds the rules the
default cannot say. A value given as text that reads as a number (``"1e-5"``) is accepted as that
number. Model, data and search-space groups are the user's own and are checked where they are read.
Imports ``config`` only lazily (no cycle).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from physmend.settings import ABOVE_ZERO, TYPED, Rule, SettingError, check, rule_of

#: groups physmend ships and owns the keys of (the user's ``model`` and ``data`` are checked on load)
CHECKED_GROUPS = ("simulate", "tracking", "diagnose", "ude", "train", "mask", "sensitivity", "symbolic",
                  "propose", "decide", "export", "discover", "sweep")

#: word settings with a closed set of values (others, like ``simulate.method``, are checked by their
#: user; those of the typed groups are rules of their settings classes)
CHOICES: dict[str, tuple[str, ...]] = {
    "export.format": ("all", "latex", "sympy", "python", "network", "petab"),
}

#: settings whose default ``auto`` has a list of names, not a number, as its alternative
AUTO_OR_LIST = ("symbolic.parameters",)

#: ``key: (low, high)``, both inclusive, where the default's kind says too little: counts that must
#: be at least one, fractions, weights that may be zero
RANGES: dict[str, tuple[float, float]] = {
    **{key: (1, math.inf) for key in (
        "diagnose.n_windows", "diagnose.smooth_samples", "mask.max_k", "mask.retrain_epochs", "sensitivity.top_k",
        "sensitivity.max_rows", "symbolic.window_samples", "sweep.n_trials", "sweep.group", "sweep.workers",
        "sweep.heartbeat_interval", "sweep.stale_after", "discover.n_trials", "discover.group", "threads")},
    "diagnose.window_fraction": (ABOVE_ZERO, 1.0),
    "sensitivity.group_r": (ABOVE_ZERO, 1.0),
    "symbolic.canonical_r2": (ABOVE_ZERO, 1.0),
    "mask.tolerance": (0.0, math.inf),
    "mask.retrain_fit_gain": (0.0, 0.5),
}


def rule_from_default(key: str, default: Any) -> Rule:
    """The rule of an untyped group's setting ``key``, from the kind of its shipped ``default``."""
    if key in CHOICES:
        return Rule("word", choices=CHOICES[key])
    if key in AUTO_OR_LIST:
        return Rule("names")
    if isinstance(default, str) and default == "auto":
        return Rule("auto")
    if isinstance(default, bool):
        return Rule("bool")
    if isinstance(default, (int, float)):
        kind = "int" if isinstance(default, int) else "float"
        if key in RANGES:
            low, high = RANGES[key]
            return Rule(kind, low=low, high=high)
        if isinstance(default, int) or default == 0:
            return Rule(kind, low=0.0) if default >= 0 else Rule(kind, low=-math.inf)
        return Rule(kind, low=None) if default > 0 else Rule(kind, low=-math.inf)
    if isinstance(default, str):
        return Rule("word")
    return Rule("any")


def check_value(key: str, value: Any, default: Any) -> Any:
    """``value`` of ``key`` checked against the kind of its shipped ``default``; returns it, as a
    number where text reads as one. Raises :class:`SettingError`."""
    if value is None or default is None or isinstance(default, (list, dict)) or OmegaConf.is_config(value):
        return value
    return check(key, value, rule_from_default(key, default))


def check_settings(cfg: DictConfig, choices: dict[str, str], conf_dir: Path) -> None:
    """Check (and normalise: numbers given as text) every setting of :data:`CHECKED_GROUPS` in ``cfg``:
    a typed group's by its settings class, another's against the shipped option file the group was
    composed from (a user's own option file of a shipped group against the shipped default)."""
    for group in CHECKED_GROUPS:
        if group not in cfg or not isinstance(cfg[group], DictConfig):
            continue
        if group in TYPED:
            _walk_typed(cfg[group], TYPED[group], group)
            continue
        path = conf_dir / group / f"{choices.get(group, 'default')}.yaml"
        if not path.is_file():
            path = conf_dir / group / "default.yaml"
        if not path.is_file():
            continue
        defaults = yaml.safe_load(path.read_text()) or {}
        _walk(cfg[group], defaults, group)
    if "seed" in cfg:
        cfg.seed = check_value("seed", cfg.seed, 0)
    if "threads" in cfg:
        cfg.threads = check_value("threads", cfg.threads, 1)
    if "device" in cfg:
        check_device(cfg.device)


def check_device(value: Any) -> None:
    """``device`` is ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (whether this machine has that device is
    checked where the problem is loaded, :func:`physmend.device.resolve_device`)."""
    text = str(value).strip().lower()
    if text in ("auto", "cpu") or re.fullmatch(r"cuda(:\d+)?", text):
        return
    raise SettingError(f"device must be auto, cpu, cuda or cuda:N (N a device number), but got {value!r}")


def _raw(node: DictConfig, key: str) -> Any:
    return node._get_node(key)._value()  # noqa: SLF001 - the raw value, interpolations unresolved


def _walk_typed(node: DictConfig, cls: type, prefix: str) -> None:
    """``node``'s keys checked by the rules of settings class ``cls`` (nested groups by theirs);
    keys it does not know are left to :meth:`physmend.settings.TrainSettings.build`."""
    import dataclasses

    for f in dataclasses.fields(cls):
        key = f.name
        if key not in node:
            continue
        value = _raw(node, key)
        if isinstance(value, str) and "${" in value:
            continue  # an interpolation: checked where it is used
        name = f"{prefix}.{key}"
        sub = f.metadata.get("group")
        if sub is not None:
            if isinstance(node[key], DictConfig):
                _walk_typed(node[key], sub, name)
            continue
        rule = rule_of(cls, key)
        if rule is None or node[key] is None or OmegaConf.is_config(node[key]):
            continue
        checked = check(name, node[key], rule)
        if isinstance(checked, tuple):
            continue  # a list: stays a list in the configuration
        if checked is not node[key]:
            node[key] = checked


def _walk(node: DictConfig, defaults: dict[str, Any], prefix: str) -> None:
    for key, default in defaults.items():
        if key not in node:
            continue
        name = f"{prefix}.{key}"
        value = _raw(node, key)
        if isinstance(value, str) and "${" in value:
            continue  # an interpolation: checked where it is used
        if isinstance(default, dict):
            if isinstance(node[key], DictConfig):
                _walk(node[key], default, name)
            continue
        checked = check_value(name, node[key], default)
        if checked is not node[key]:
            node[key] = checked


# -- the operators config group (physmend.symbolic.operators prices and maps them) ----------------------
#: operator name -> (arity, what it is); the names every back end maps from
KNOWN: dict[str, tuple[int, str]] = {
    "add": (2, "a + b"),
    "sub": (2, "a - b"),
    "mul": (2, "a·b (products of states, inputs and parameters)"),
    "div": (2, "a / b (quotients)"),
    "square": (1, "a²"),
    "abs": (1, "|a|"),
    "sqrt": (1, "sqrt(|a|) (with mul: the signed power a·|a|^½)"),
    "sign": (1, "sign(a) (Coulomb friction, switching loads)"),
    "min": (2, "min(a, b) (saturation, clipping, thresholds)"),
    "max": (2, "max(a, b) (overflow, one-way flow)"),
    "exp": (1, "exp(a)"),
    "log": (1, "log(|a|)"),
    "tanh": (1, "tanh(a) (smooth saturation)"),
    "sin": (1, "sin(a) of a phase a (an angle: pendulums, cranks, rotating frames)"),
    "cos": (1, "cos(a) of a phase a (an angle)"),
    "pow": (2, "|a|^c, c a fitted exponent (power laws: turbulent drag, creep, flow curves)"),
}


class OperatorError(ValueError):
    """An operators file or setting is wrong; the message names the file and the entry."""


def check_operators(ops: Any, where: str) -> dict[str, int]:
    """``ops`` (a mapping name -> price) checked; ``where`` names the file or key for the message."""
    if ops is None:
        raise OperatorError(f"{where}: no operators given; list at least one, e.g. 'add: 1'")
    if not isinstance(ops, Mapping):
        raise OperatorError(f"{where} must map operator names to prices (e.g. 'mul: 1'), but got {type(ops).__name__}")
    out: dict[str, int] = {}
    for name, price in ops.items():
        name = str(name)
        if name not in KNOWN:
            raise OperatorError(f"{where}: unknown operator {name!r} (known: {', '.join(KNOWN)})")
        if price is None:
            continue  # listed and switched off ('sign: null')
        if isinstance(price, bool) or not isinstance(price, int) or price < 1:
            raise OperatorError(f"{where}: the price of {name!r} must be a whole number ≥ 1, but got {price!r}")
        out[name] = int(price)
    if not out:
        raise OperatorError(f"{where}: every operator is switched off; keep at least one (e.g. 'add: 1')")
    return out
