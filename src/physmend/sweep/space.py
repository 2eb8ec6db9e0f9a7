"""Search spaces: the YAML files of ``sweeps/`` (or the user's own), parsed and checked, and
sampled into Hydra overrides.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import OmegaConf

from physmend.config import ConfigError

if TYPE_CHECKING:
    import optuna


KINDS = ("choice", "uniform", "log_uniform", "int")

_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")

_PLAIN = re.compile(r"[A-Za-z_][A-Za-z0-9_\-/.]*")

_RESERVED = {"true", "false", "null", "inf", "nan", "none"}



@dataclass(frozen=True)
class Param:
    """One searched config key: ``kind`` is choice | uniform | log_uniform | int."""

    key: str
    kind: str
    choices: tuple[Any, ...] = ()
    low: float = 0.0
    high: float = 0.0
    step: float | None = None
    log: bool = False

    def suggest(self, trial: "optuna.Trial") -> Any:
        """Ask ``trial`` for a value of this parameter."""
        if self.kind == "choice":
            return trial.suggest_categorical(self.key, list(self.choices))
        if self.kind == "int":
            return trial.suggest_int(self.key, int(self.low), int(self.high), step=int(self.step or 1), log=self.log)
        return trial.suggest_float(self.key, self.low, self.high, step=self.step, log=self.kind == "log_uniform")

    def contains(self, value: Any) -> bool:
        """Whether ``value`` is a possible value of this parameter."""
        if self.kind == "choice":
            return any(_same(value, c) for c in self.choices)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.kind == "int" and not isinstance(value, int):
            return False
        return self.low <= value <= self.high

    def examples(self) -> list[Any]:
        """Values that exercise this parameter when composing: every choice, or both bounds."""
        if self.kind == "choice":
            return list(self.choices)
        if self.kind == "int":
            return [int(self.low), int(self.high)]
        return [self.low, self.high]

    def spec(self) -> dict[str, Any]:
        """The parameter as written in a space file (normalised)."""
        out: dict[str, Any] = {self.kind: list(self.choices) if self.kind == "choice" else [self.low, self.high]}
        if self.step is not None:
            out["step"] = self.step
        if self.log:
            out["log"] = True
        return out



@dataclass(frozen=True)
class SearchSpace:
    """A named search space: ``params`` by config key, ``first_trials`` to enqueue first."""

    name: str
    label: str
    description: str
    params: dict[str, Param]
    first_trials: tuple[dict[str, Any], ...] = ()

    def suggest(self, trial: "optuna.Trial") -> dict[str, Any]:
        """The trial's value for every parameter."""
        return {key: p.suggest(trial) for key, p in self.params.items()}

    def without(self, keys: Sequence[str]) -> SearchSpace:
        """This space no longer searching ``keys`` (dropped from its params and first trials)."""
        drop = set(keys)
        return SearchSpace(self.name, self.label, self.description,
                           {k: p for k, p in self.params.items() if k not in drop},
                           tuple({k: v for k, v in t.items() if k not in drop} for t in self.first_trials))

    def spec(self) -> dict[str, Any]:
        """The space as plain data (logged as ``space.yaml``, compared on resume)."""
        return {
            "description": self.description,
            "params": {k: p.spec() for k, p in self.params.items()},
            "first_trials": [dict(t) for t in self.first_trials],
        }



def _same(a: Any, b: Any) -> bool:
    """Equal as config values: numbers by value (4 == 4.0), but never a boolean and a number."""
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return type(a) is type(b) and a == b
    return a == b



def hydra_value(value: Any) -> str:
    """``value`` written as a Hydra override value (strings quoted where they would not stay strings)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    text = str(value)
    if _PLAIN.fullmatch(text) and text.lower() not in _RESERVED:
        return text
    return "'" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"



def trial_overrides(values: dict[str, Any]) -> list[str]:
    """Hydra overrides ``key=value`` for a trial's parameter values."""
    return [f"{key}={hydra_value(v)}" for key, v in values.items()]



def available_spaces() -> list[str]:
    """Names of the search spaces shipped in physmend's ``sweeps/`` folder."""
    from physmend.config import sweeps_dir

    return sorted(p.stem for p in sweeps_dir().glob("*.yaml"))



def resolve_space(ref: str) -> tuple[Path, str, str]:
    """``(file, name, label)`` for ``sweep.space``: a shipped space name or a YAML file path."""
    from physmend.config import sweeps_dir

    ref = str(ref)
    shipped = sweeps_dir() / f"{ref}.yaml"
    if "/" not in ref and not ref.endswith((".yaml", ".yml")) and shipped.is_file():
        return shipped, ref, f"sweeps/{ref}.yaml"
    path = Path(ref).expanduser()
    if path.is_file():
        return path.resolve(), path.stem, str(path)
    raise ConfigError(
        f"sweep.space must name a search space shipped with physmend ({', '.join(available_spaces())}) "
        f"or an existing YAML file, but got {ref!r}"
    )



def load_space(ref: str) -> SearchSpace:
    """Load and check the search space ``ref`` (see :func:`resolve_space`); errors name file and key."""
    path, name, label = resolve_space(ref)
    try:
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    except Exception as exc:  # noqa: BLE001 - YAML syntax errors of every flavour
        raise ConfigError(f"{label}: not a valid YAML file: {exc}") from None
    return parse_space(raw, name=name, label=label)



def parse_space(raw: Any, *, name: str, label: str) -> SearchSpace:
    """Check a search space given as plain data; ``label`` names it in errors."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{label}: a search space must be a mapping with 'params', but got {type(raw).__name__}")
    unknown = sorted(set(raw) - {"description", "params", "first_trials"})
    if unknown:
        raise ConfigError(f"{label}: unknown top-level keys {unknown}; allowed: description, params, first_trials")
    params_raw = raw.get("params")
    if not isinstance(params_raw, dict) or not params_raw:
        raise ConfigError(f"{label}: 'params' must be a non-empty mapping of config key -> {{kind: values}}, but got {params_raw!r}")
    params = {str(k): _parse_param(str(k), v, label) for k, v in params_raw.items()}
    first = _parse_first_trials(raw.get("first_trials") or [], params, label)
    return SearchSpace(name=name, label=label, description=str(raw.get("description") or ""), params=params, first_trials=first)



def _parse_param(key: str, spec: Any, label: str) -> Param:
    where = f"{label}: params.{key}"
    if not _KEY.fullmatch(key):
        raise ConfigError(f"{where}: a parameter must be a config key like 'train.lr', but got {key!r}")
    if not isinstance(spec, dict):
        raise ConfigError(f"{where} must be a mapping like {{choice: [...]}}, but got {spec!r}")
    kinds = [k for k in spec if k in KINDS]
    if len(kinds) != 1:
        raise ConfigError(f"{where} needs exactly one of {', '.join(KINDS)}, but got keys {sorted(map(str, spec))}")
    kind = kinds[0]
    extra = sorted(set(spec) - {kind} - _MODIFIERS[kind])
    if extra:
        allowed = sorted(_MODIFIERS[kind]) or "none"
        raise ConfigError(f"{where}: unknown keys {extra} for {kind} (allowed besides {kind}: {allowed})")
    return _PARSERS[kind](key, spec, f"{where}.{kind}")



def _parse_choice(key: str, spec: dict[str, Any], where: str) -> Param:
    values = spec["choice"]
    if not isinstance(values, list) or not values:
        raise ConfigError(f"{where} needs a non-empty list of values, but got {values!r}")
    for v in values:
        if v is not None and not isinstance(v, (bool, int, float, str)):
            raise ConfigError(f"{where} values must be numbers, strings, booleans or null, but got {v!r}")
    dupes = [v for i, v in enumerate(values) if any(_same(v, w) for w in values[:i])]
    if dupes:
        raise ConfigError(f"{where} values must be distinct, but {dupes} repeat in {values}")
    return Param(key, "choice", choices=tuple(values))



def _bounds(spec: dict[str, Any], kind: str, where: str, rule: str) -> tuple[Any, Any]:
    bounds = spec[kind]
    ok = isinstance(bounds, list) and len(bounds) == 2
    ok = ok and all(isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds)
    if not ok:
        raise ConfigError(f"{where} needs [low, high] with {rule}, but got {bounds!r}")
    return bounds[0], bounds[1]



def _parse_uniform(key: str, spec: dict[str, Any], where: str) -> Param:
    low, high = _bounds(spec, "uniform", where, "low <= high")
    if not low <= high:
        raise ConfigError(f"{where} needs low <= high, but got {[low, high]}")
    step = spec.get("step")
    if step is not None and not (isinstance(step, (int, float)) and not isinstance(step, bool) and step > 0):
        raise ConfigError(f"{where}: step must be a number > 0, but got {step!r}")
    return Param(key, "uniform", low=float(low), high=float(high), step=None if step is None else float(step))



def _parse_log_uniform(key: str, spec: dict[str, Any], where: str) -> Param:
    low, high = _bounds(spec, "log_uniform", where, "0 < low <= high")
    if not 0 < low <= high:
        raise ConfigError(f"{where} needs 0 < low <= high, but got {[low, high]}")
    return Param(key, "log_uniform", low=float(low), high=float(high))



def _parse_int(key: str, spec: dict[str, Any], where: str) -> Param:
    low, high = _bounds(spec, "int", where, "integers low <= high")
    if not (isinstance(low, int) and isinstance(high, int) and low <= high):
        raise ConfigError(f"{where} needs integers low <= high, but got {[low, high]}")
    step, log = spec.get("step", 1), spec.get("log", False)
    if not (isinstance(step, int) and not isinstance(step, bool) and step >= 1):
        raise ConfigError(f"{where}: step must be an integer >= 1, but got {step!r}")
    if not isinstance(log, bool):
        raise ConfigError(f"{where}: log must be true or false, but got {log!r}")
    if log and (low < 1 or step != 1):
        raise ConfigError(f"{where}: log: true needs low >= 1 and step 1, but got low {low}, step {step}")
    return Param(key, "int", low=low, high=high, step=None if step == 1 else step, log=log)



_PARSERS: dict[str, Callable[[str, dict[str, Any], str], Param]] = {
    "choice": _parse_choice,
    "uniform": _parse_uniform,
    "log_uniform": _parse_log_uniform,
    "int": _parse_int,
}

_MODIFIERS: dict[str, set[str]] = {"choice": set(), "uniform": {"step"}, "log_uniform": set(), "int": {"step", "log"}}



def _parse_first_trials(raw: Any, params: dict[str, Param], label: str) -> tuple[dict[str, Any], ...]:
    if not isinstance(raw, list):
        raise ConfigError(f"{label}: first_trials must be a list of {{key: value}} mappings, but got {raw!r}")
    out = []
    for i, entry in enumerate(raw):
        where = f"{label}: first_trials[{i}]"
        if not isinstance(entry, dict) or not entry:
            raise ConfigError(f"{where} must be a non-empty mapping of searched keys to values, but got {entry!r}")
        for key, value in entry.items():
            if key not in params:
                raise ConfigError(f"{where}: {key!r} is not a searched parameter (params: {sorted(params)})")
            if not params[key].contains(value):
                raise ConfigError(f"{where}: {key}={value!r} lies outside params.{key} {params[key].spec()}")
        out.append(dict(entry))
    return tuple(out)
