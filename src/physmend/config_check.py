"""Settings checked when the configuration is composed, before any run or file is written.

Every setting of a shipped group (``train``, ``simulate``, ``sweep`` …) keeps the kind of its
shipped default: a whole number stays a whole number ≥ 0, a number a finite number (> 0 where the
default is positive, ≥ 0 where it is zero), a switch ``true``/``false``, a word a word (and, for
the keys in :data:`CHOICES`, one of the listed words); a default ``auto`` accepts ``auto`` or a
number > 0. :data:`RANGES` adds the rules the default cannot say. A value given as text that reads as a
number (``"1e-5"``) is accepted as that number. Model, data and search-space groups are the
user's own and are checked where they are read. Imports ``config`` only lazily (no cycle).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

#: groups physmend ships and owns the keys of (the user's ``model`` and ``data`` are checked on load)
CHECKED_GROUPS = ("simulate", "tracking", "diagnose", "ude", "train", "mask", "sensitivity", "symbolic",
                  "propose", "decide", "export", "discover", "sweep")

#: word settings with a closed set of values (others, like ``simulate.method``, are checked by their user)
CHOICES: dict[str, tuple[str, ...]] = {
    "train.schedule": ("cosine", "none"),
    "train.warm_start": ("auto", "none"),
    "train.segment_starts": ("chained", "forced"),
    "ude.units": ("equation", "state"),
    "export.format": ("all", "latex", "sympy", "python", "network", "petab"),
    "simulate.dtype": ("float64", "float32"),
}

#: a lower bound meaning "above zero" (an open interval: shown as ``(0, high]``)
ABOVE_ZERO = math.ulp(0.0)

#: settings whose default ``auto`` has a list of names, not a number, as its alternative
AUTO_OR_LIST = ("symbolic.parameters", "ude.inputs.parameters", "ude.inputs.observed")

#: switches whose alternative is a list of names (checked against the model where it is used)
SWITCH_OR_LIST = ("ude.inputs.states", "ude.inputs.inputs")

#: the widest hidden layer and the most hidden layers a network may have (``ude.width``, ``ude.depth``),
#: generous bounds (a sweep's shipped spaces search widths 4-64 and 1-3 layers) that keep any network,
#: and one read back from a store, under ~150 MB of weights: ``hybrid.json`` is checked against them
#: before its network is built (:mod:`physmend.ude.stored_spec`)
MAX_UNITS = 1024
MAX_LAYERS = 16

#: ``key: (low, high)``, both inclusive, where the default's kind says too little: counts that must
#: be at least one, fractions, weights that may be zero
RANGES: dict[str, tuple[float, float]] = {
    **{key: (1, math.inf) for key in (
        "train.epochs", "train.eval_every", "train.segment_samples", "train.warm_window_samples",
        "diagnose.n_windows", "diagnose.smooth_samples", "mask.max_k", "mask.retrain_epochs", "sensitivity.top_k",
        "sensitivity.max_rows", "symbolic.window_samples", "sweep.n_trials", "sweep.group", "sweep.workers",
        "sweep.heartbeat_interval", "sweep.stale_after", "discover.n_trials", "discover.group", "threads")},
    "ude.width": (1, MAX_UNITS),
    "ude.depth": (0, MAX_LAYERS),
    "diagnose.window_fraction": (ABOVE_ZERO, 1.0),
    "sensitivity.group_r": (ABOVE_ZERO, 1.0),
    "symbolic.canonical_r2": (ABOVE_ZERO, 1.0),
    "mask.tolerance": (0.0, math.inf),
    "mask.retrain_fit_gain": (0.0, 0.5),
    "train.patience_fit_gain": (0.0, 0.5),
    "train.continuity_weight": (0.0, math.inf),
    "train.restarts": (0, math.inf),
    "train.polish": (0.0, math.inf),
}

class SettingError(ValueError):
    """A setting has the wrong kind or range; the message names the key, the value and the rule."""


def _as_number(value: Any) -> float | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _rule(key: str, default: Any) -> str:
    if isinstance(default, bool):
        return "true or false"
    low, high = RANGES.get(key, (0.0 if isinstance(default, int) or default == 0 else None, math.inf))
    kind = "a whole number" if isinstance(default, int) else "a number"
    if low is None:
        return f"{kind} > 0"
    if low == ABOVE_ZERO:
        return f"{kind} in (0, {high:g}]"
    return f"{kind} ≥ {low:g}" if high == math.inf else f"{kind} in [{low:g}, {high:g}]"


def _allowed(key: str, default: Any, number: float) -> bool:
    if key in RANGES:
        low, high = RANGES[key]
        return low <= number <= high
    if isinstance(default, int) or default == 0:
        return number >= 0 if default >= 0 else True
    return number > 0 if default > 0 else True


def check_value(key: str, value: Any, default: Any) -> Any:
    """``value`` of ``key`` checked against the kind of its shipped ``default``; returns it, as a
    number where text reads as one. Raises :class:`SettingError`."""
    if value is None or default is None or isinstance(default, (list, dict)) or OmegaConf.is_config(value):
        return value
    if key in CHOICES:
        if value not in CHOICES[key]:
            raise SettingError(f"{key} must be one of {list(CHOICES[key])}, but got {value!r}")
        return value
    if key in AUTO_OR_LIST:
        return value  # 'auto' or a list of names: checked against the model where it is used
    if key in SWITCH_OR_LIST and not isinstance(value, bool):
        raise SettingError(f"{key} must be true, false or a list of names/patterns, but got {value!r}")
    if isinstance(default, str) and default == "auto":
        if value == "auto":
            return value
        number = _as_number(value)
        if number is None or not math.isfinite(number) or number <= 0:
            raise SettingError(f"{key} must be 'auto' or a number > 0, but got {value!r}")
        return number
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise SettingError(f"{key} must be true or false, but got {value!r}")
        return value
    if isinstance(default, (int, float)):
        number = _as_number(value)
        if (number is None or not math.isfinite(number) or (isinstance(default, int) and number != int(number))
                or not _allowed(key, default, number)):
            raise SettingError(f"{key} must be {_rule(key, default)}, but got {value!r}")
        return int(number) if isinstance(default, int) else number
    if isinstance(default, str):
        if not isinstance(value, str):
            raise SettingError(f"{key} must be a word, but got {value!r}")
    return value


def check_settings(cfg: DictConfig, choices: dict[str, str], conf_dir: Path) -> None:
    """Check (and normalise: numbers given as text) every setting of :data:`CHECKED_GROUPS` in ``cfg``
    against the shipped option file the group was composed from; a user's own option file of a
    shipped group is checked against the shipped default."""
    for group in CHECKED_GROUPS:
        if group not in cfg or not isinstance(cfg[group], DictConfig):
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


def _walk(node: DictConfig, defaults: dict[str, Any], prefix: str) -> None:
    for key, default in defaults.items():
        if key not in node:
            continue
        name = f"{prefix}.{key}"
        value = node._get_node(key)._value()  # noqa: SLF001 - the raw value, interpolations unresolved
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
