"""Typed settings of the groups training reads (``train``, ``ude``, ``simulate``), built once.

Each group is a frozen dataclass whose fields are the group's keys. Its defaults live in one place,
the shipped YAML (``conf/<group>/default.yaml``): a key missing from a configuration built in code
gets its shipped default, never a default of the code's. Every rule (kind, range, choices) is a
field's :class:`Rule`, checked when the settings are built (:func:`training_settings`) and when a
configuration is composed (:mod:`physmend.config_check` asks :data:`TYPED` for these groups).

``auto`` times (``train.step``, ``train.segment_length``, ``train.warm_window``) are resolved once
per training by :func:`physmend.ude.timescale.resolve_settings` (the rules are there).

A :class:`TrainingSettings` reads like the configuration it came from (``s.train.lr``,
``s.ude.inputs.states``, ``s.simulate.method``, ``s.seed``), so code that takes either reads both.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import yaml
from omegaconf import OmegaConf

from physmend.exceptions import PhysmendError

AUTO = "auto"


class SettingError(PhysmendError, ValueError):
    """A setting has the wrong kind or range; the message names the key, the value and the rule."""


#: a lower bound meaning "above zero" (an open interval: shown as ``(0, high]``)
ABOVE_ZERO = math.ulp(0.0)


@dataclass(frozen=True)
class Rule:
    """How one setting is checked.

    ``kind``: ``int`` (a whole number), ``float`` (a finite number), ``bool`` (true/false), ``word``
    (text; one of ``choices`` where given), ``list`` (a list of names), ``auto`` (``'auto'`` or a number > 0), ``names``
    (``'auto'`` or a list of names, checked against the model where used), ``switch`` (true, false
    or a list of names), ``any`` (not checked here). ``low``/``high``: inclusive bounds of a number
    (``low`` None: > 0).
    """

    kind: str
    low: float | None = 0.0
    high: float = math.inf
    choices: tuple[str, ...] = ()

    def text(self) -> str:
        """The rule in words, as messages state it (``a whole number ≥ 1``, ``a number in (0, 1]``)."""
        if self.kind == "bool":
            return "true or false"
        what = "a whole number" if self.kind == "int" else "a number"
        if self.low is None:
            return f"{what} > 0"
        if self.low == ABOVE_ZERO:
            return f"{what} in (0, {self.high:g}]"
        return f"{what} ≥ {self.low:g}" if self.high == math.inf else f"{what} in [{self.low:g}, {self.high:g}]"

    def allows(self, number: float) -> bool:
        if self.low is None:
            return number > 0 and number <= self.high
        return self.low <= number <= self.high


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


def check(key: str, value: Any, rule: Rule) -> Any:
    """``value`` of ``key`` checked by ``rule``; returns it (a number where text reads as one, a
    list as a tuple). Raises :class:`SettingError` naming the key, the rule and the value."""
    if rule.kind == "any" or value is None and rule.kind in ("names", "switch"):
        return value
    if rule.kind == "list":
        if isinstance(value, (list, tuple)):
            return tuple(value)
        raise SettingError(f"{key} must be a list of names/patterns, but got {value!r}")
    if rule.kind == "names":
        if isinstance(value, str):
            return value  # 'auto' (anything else: checked against the model where it is used)
        if isinstance(value, (list, tuple)):
            return tuple(value)
        raise SettingError(f"{key} must be 'auto' or a list of names/patterns, but got {value!r}")
    if rule.kind == "switch":
        if isinstance(value, bool):
            return value
        if isinstance(value, (list, tuple)):
            return tuple(value)
        raise SettingError(f"{key} must be true, false or a list of names/patterns, but got {value!r}")
    if rule.kind == "word":
        if rule.choices:
            if value not in rule.choices:
                raise SettingError(f"{key} must be one of {list(rule.choices)}, but got {value!r}")
            return value
        if not isinstance(value, str):
            raise SettingError(f"{key} must be a word, but got {value!r}")
        return value
    if rule.kind == "auto":
        if value is None or value == AUTO:
            return AUTO
        number = _as_number(value)
        if number is None or not math.isfinite(number) or number <= 0:
            raise SettingError(f"{key} must be 'auto' or a number > 0, but got {value!r}")
        return number
    if rule.kind == "bool":
        if not isinstance(value, bool):
            raise SettingError(f"{key} must be true or false, but got {value!r}")
        return value
    if rule.kind in ("int", "float"):
        number = _as_number(value)
        if (number is None or not math.isfinite(number) or (rule.kind == "int" and number != int(number))
                or not rule.allows(number)):
            raise SettingError(f"{key} must be {rule.text()}, but got {value!r}")
        return int(number) if rule.kind == "int" else number
    raise AssertionError(f"unknown rule kind {rule.kind!r}")


def setting(kind: str, *, low: float | None = 0.0, high: float = math.inf, choices: tuple[str, ...] = ()) -> Any:
    """A dataclass field checked by ``Rule(kind, low, high, choices)`` (no code default: the YAML has it)."""
    return field(metadata={"rule": Rule(kind, low, high, choices)})


def rule_of(cls: type, key: str) -> Rule | None:
    """The rule of field ``key`` of settings class ``cls`` (None: not one of its keys)."""
    for f in dataclasses.fields(cls):
        if f.name == key:
            return f.metadata.get("rule")
    return None


def shipped_dir(name: str) -> Path:
    """A directory physmend ships (``conf``, ``sweeps``, ``examples``): inside the installed package,
    or beside ``src/`` in a checkout."""
    here = Path(__file__).resolve().parent
    for candidate in (here / name, here.parents[1] / name):
        if candidate.is_dir():
            return candidate
    raise SettingError(f"physmend's {name}/ directory is missing (looked in {here / name} and {here.parents[1] / name})")


@functools.lru_cache(maxsize=None)
def _shipped(group: str) -> dict[str, Any]:
    path = shipped_dir("conf") / group / "default.yaml"
    return yaml.safe_load(path.read_text()) or {}


@functools.lru_cache(maxsize=None)
def _shipped_top() -> dict[str, Any]:
    return yaml.safe_load((shipped_dir("conf") / "config.yaml").read_text()) or {}


def shipped_group(group: str) -> dict[str, Any]:
    """The shipped defaults of ``group`` (``conf/<group>/default.yaml``), a copy."""
    import copy

    return copy.deepcopy(_shipped(group))


def shipped_default(group: str, key: str) -> Any:
    """The shipped default of ``group.key`` (``key`` dotted for nested keys), from ``conf/<group>/default.yaml``."""
    node: Any = _shipped(group)
    for part in key.split("."):
        node = node[part]
    return node


def _plain(node: Any) -> dict[str, Any]:
    if node is None:
        return {}
    if OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
    if isinstance(node, Mapping):
        return dict(node)
    if dataclasses.is_dataclass(node):
        return {f.name: getattr(node, f.name) for f in dataclasses.fields(node)}
    raise SettingError(f"settings must be a mapping of keys to values, but got {type(node).__name__}")


class _Group:
    """Building a settings class from a configuration group (a mapping), checked."""

    GROUP: ClassVar[str]

    @classmethod
    def build(cls, node: Any, prefix: str | None = None) -> Any:
        """The settings of ``node`` (a DictConfig, a mapping, or already these settings); a missing key
        gets its shipped default, an unknown key or a value against its rule is a :class:`SettingError`."""
        if isinstance(node, cls):
            return node
        prefix = prefix or cls.GROUP
        raw = _plain(node)
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(raw) - set(fields))
        if unknown:
            raise SettingError(f"{prefix}.{unknown[0]} is not a setting of {prefix}; the settings are: "
                               f"{', '.join(fields)}")
        values: dict[str, Any] = {}
        for name, f in fields.items():
            key = f"{prefix}.{name}"
            value = raw[name] if name in raw else shipped_default(cls.GROUP, key.split(".", 1)[1])
            sub = f.metadata.get("group")
            if sub is not None:
                values[name] = sub.build(value, key)
            else:
                values[name] = check(key, value, f.metadata["rule"])
        return cls(**values)


@dataclass(frozen=True)
class TrainSettings(_Group):
    """``train.*``: multiple-shooting training (see ``conf/train/default.yaml`` for each key's meaning).

    Times are in the data's time unit; ``step``, ``segment_length`` and ``warm_window`` are
    ``'auto'`` or a number until :meth:`TrainingSettings.resolved` makes them numbers.
    """

    GROUP: ClassVar[str] = "train"

    epochs: int = setting("int", low=1)
    lr: float = setting("float", low=None)
    weight_decay: float = setting("float")
    schedule: str = setting("word", choices=("cosine", "none"))
    step: float | str = setting("auto")
    segment_length: float | str = setting("auto")
    segment_samples: int = setting("int", low=1)
    continuity_weight: float = setting("float")
    eval_every: int = setting("int", low=1)
    patience: int = setting("int")
    patience_fit_gain: float = setting("float", high=0.5)
    polish: float = setting("float")
    restarts: int = setting("int")
    estimate_parameters: bool = setting("bool")
    warm_start: str = setting("word", choices=("auto", "none"))
    warm_iterations: int = setting("int")
    warm_window: float | str = setting("auto")
    warm_window_samples: int = setting("int", low=1)
    segment_starts: str = setting("word", choices=("chained", "forced"))
    warmup_epochs: int = setting("int")
    sparsity: float = setting("float")
    backward: str = setting("word", choices=("autograd", "adjoint"))
    memory_limit_gib: float = setting("float", low=None)

    @property
    def chained(self) -> bool:
        """``segment_starts == 'chained'``: after a warm start, segments start where the previous one ends."""
        return self.segment_starts == "chained"

    @property
    def cycles(self) -> int:
        """Cycles of ``epochs`` a model may get: the first and ``restarts`` more."""
        return 1 + self.restarts

    @property
    def polish_iterations(self) -> int:
        """L-BFGS iterations after Adam: ``polish`` as a share of ``epochs`` (0: none)."""
        return int(round(self.polish * self.epochs))

    @property
    def warm_window_steps(self) -> int:
        """The warm-start window in training steps (at least 1; times resolved)."""
        return max(1, int(round(float(self.warm_window) / float(self.step))))


#: the widest hidden layer and the most hidden layers a network may have (``ude.width``, ``ude.depth``),
#: generous bounds (a sweep's shipped spaces search widths 4-64 and 1-3 layers) that keep any network,
#: and one read back from a store, under ~150 MB of weights: ``hybrid.json`` is checked against them
#: before its network is built (:mod:`physmend.ude.stored_spec`)
MAX_UNITS = 1024
MAX_LAYERS = 16


@dataclass(frozen=True)
class InputsSettings(_Group):
    """``ude.inputs.*``: the network's inputs (lists of names/patterns as tuples)."""

    GROUP: ClassVar[str] = "ude"

    states: bool | tuple[str, ...] = setting("switch")
    observed: str | tuple[str, ...] = setting("names")
    inputs: bool | tuple[str, ...] = setting("switch")
    parameters: str | tuple[str, ...] = setting("names")


@dataclass(frozen=True)
class UdeSettings(_Group):
    """``ude.*``: the hybrid model (see ``conf/ude/default.yaml``)."""

    GROUP: ClassVar[str] = "ude"

    corrected: tuple[str, ...] = setting("list")
    inputs: InputsSettings = field(metadata={"group": InputsSettings})
    width: int = setting("int", low=1, high=MAX_UNITS)
    depth: int = setting("int", low=0, high=MAX_LAYERS)
    activation: str = setting("word")  # checked against the activations where the network is built
    units: str = setting("word", choices=("equation", "state"))
    output_scale: float = setting("float", low=None)


@dataclass(frozen=True)
class SimulateSettings(_Group):
    """``simulate.*``: whole-trajectory simulation (see ``conf/simulate/default.yaml``)."""

    GROUP: ClassVar[str] = "simulate"

    method: str = setting("word")  # checked by the solver registry
    rtol: float = setting("float", low=None)
    atol: float = setting("float", low=None)
    dtype: str = setting("word", choices=("float64", "float32"))
    options: dict[str, Any] = setting("any")

    def solver(self) -> dict[str, Any]:
        """The solver options of every whole-trajectory simulation (``method``, ``rtol``, ``atol``, ``options``)."""
        return {"method": str(self.method), "rtol": float(self.rtol), "atol": float(self.atol),
                "options": dict(self.options or {})}


#: the typed groups, by name (the composed configuration is checked by them: :mod:`physmend.config_check`)
TYPED: dict[str, type] = {"train": TrainSettings, "ude": UdeSettings, "simulate": SimulateSettings}


@dataclass(frozen=True)
class TrainingSettings:
    """Everything a training reads: ``seed`` and the ``train``, ``ude`` and ``simulate`` groups."""

    seed: int
    train: TrainSettings
    ude: UdeSettings
    simulate: SimulateSettings

    @property
    def times_resolved(self) -> bool:
        t = self.train
        return not any(v == AUTO for v in (t.step, t.segment_length, t.warm_window))


def training_settings(cfg: Any) -> TrainingSettings:
    """The :class:`TrainingSettings` of ``cfg`` (a composed or hand-built configuration; returned as
    is when it is one already). A missing group or key gets its shipped default; a missing ``seed`` the one of ``conf/config.yaml``."""
    if isinstance(cfg, TrainingSettings):
        return cfg
    get = cfg.get if hasattr(cfg, "get") else (lambda key, default=None: getattr(cfg, key, default))
    seed = get("seed", None)
    seed = check("seed", _shipped_top()["seed"] if seed is None else seed, Rule("int"))
    return TrainingSettings(seed=seed, train=TrainSettings.build(get("train", None)),
                            ude=UdeSettings.build(get("ude", None)),
                            simulate=SimulateSettings.build(get("simulate", None)))
