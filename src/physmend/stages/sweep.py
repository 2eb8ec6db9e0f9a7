"""``physmend sweep``: an Optuna study over UDE architectures and training settings.

Each trial is a child MLflow run (``trial-NNNN``) under the sweep's parent run; the best finished
trial by ``val.rmse`` is recorded on the parent as the automatic choice and the selection (see
:mod:`physmend.tracking.selection`). physmend owns the study loop (ask → compose → train → tell)
so that it can prune from intermediate validation errors, resume, and run as many workers.

Search spaces
    ``sweeps/<name>.yaml`` (shipped) or a path to your own YAML file::

        description: what the space explores
        params:
          ude.width: {choice: [16, 32, 64]}
          train.lr: {log_uniform: [0.001, 0.03]}
          train.weight_decay: {uniform: [0.0, 1.0e-3]}
          ude.depth: {int: [1, 3]}                  # optional: step: 1, log: false
        first_trials:                                # optional: tried before the sampler proposes
          - {ude.width: 32, train.lr: 0.01}

    Each trial's values become Hydra overrides (``key=value``) composed on top of the sweep's
    own overrides, so every trial's config is a real composed config.

Resume and workers
    The study lives in ``tracking.optuna_storage`` under ``sweep.study_name`` (default
    ``<model>-<data>-<space>``). Running the same command again continues it: it runs only the
    trials still missing from ``sweep.n_trials``, under the same parent run (its ID is a study user
    attribute). Any number of processes may run the same command on one storage: before each
    trial a worker counts the trials that reached a verdict (COMPLETE, PRUNED, FAIL) plus those
    running, and stops when ``n_trials`` is reached; a trial asked in a race beyond ``n_trials`` is
    closed at once as FAIL with ``fail_reason=surplus``.

Interrupted trials
    A trial whose worker stopped (killed, machine lost) stays RUNNING in the storage. Each
    running trial records its worker (host, PID) and a heartbeat (every
    ``sweep.heartbeat_interval`` s). A worker about to ask for a trial marks stale ones FAIL with
    ``fail_reason=interrupted`` (and their child runs KILLED): trials of a dead process on the same
    host at once, others after ``sweep.stale_after`` s without a heartbeat. Interrupted trials
    (and Ctrl-C'd ones) reached no verdict, so they do not count towards ``n_trials``: resuming
    runs a fresh trial in their place. They are not re-enqueued — a configuration that crashed
    its worker is not retried blindly.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.config import ConfigError

if TYPE_CHECKING:
    import optuna

    from physmend.problem import Problem
    from physmend.tracking import Store

STAGE = "sweep"
KINDS = ("choice", "uniform", "log_uniform", "int")
SAMPLERS = ("tpe", "random")
PRUNERS = ("median", "halving", "none")
RUN_ID_ATTR = "mlflow_run_id"  # Optuna trial user attr: the trial's MLflow run ID
PARENT_ATTR = "mlflow_parent_run_id"  # Optuna study user attr: the sweep's parent run ID
CONFIG_ATTR = "physmend_config"  # Optuna study user attr: what the study was started with
WORKER_ATTR = "worker"
HEARTBEAT_ATTR = "heartbeat"
REASON_ATTR = "fail_reason"
UNCOUNTED = ("interrupted", "surplus")  # FAIL reasons that are no verdict on the trial's parameters
PARENT_WAIT_S = 20.0  # how long a worker waits for the study's creator to write the parent run ID
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")
_PLAIN = re.compile(r"[A-Za-z_][A-Za-z0-9_\-/.]*")
_RESERVED = {"true", "false", "null", "inf", "nan", "none"}
# config groups whose values make trials comparable: resuming a study with others is refused
_COMPARED = ("model", "data", "simulate", "ude", "train", "seed")


# -- search spaces -------------------------------------------------------------------------------
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


# -- settings ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Settings:
    """``cfg.sweep``, checked on construction."""

    space: str
    n_trials: int
    study_name: str | None
    sampler: str
    n_startup_trials: int
    pruner: str
    pruner_startup_trials: int
    pruner_warmup_epochs: int
    pruner_min_epochs: int
    seed: int
    timeout: float | None
    heartbeat_interval: float
    stale_after: float
    max_failures_in_a_row: int
    progress: bool
    group: int = 1
    figures: bool = True
    workers: int = 1
    group_shapes: bool = True

    @classmethod
    def from_cfg(cls, sweep: Any) -> Settings:
        def number(key: str, cast: Callable[[Any], Any], minimum: float, *, optional: bool = False) -> Any:
            value = sweep.get(key)
            if value is None and optional:
                return None
            try:
                out = cast(value)
            except (TypeError, ValueError):
                raise ConfigError(f"sweep.{key} must be a number >= {minimum}, but got {value!r}") from None
            if not out >= minimum:
                raise ConfigError(f"sweep.{key} must be >= {minimum}, but got {value!r}")
            return out

        def flag(key: str, default: bool) -> bool:
            value = sweep.get(key, default)
            if not isinstance(value, bool):
                raise ConfigError(f"sweep.{key} must be true or false, but got {value!r}")
            return value

        sampler, pruner = str(sweep.get("sampler", "tpe")), str(sweep.get("pruner", "median"))
        if sampler not in SAMPLERS:
            raise ConfigError(f"sweep.sampler must be one of {list(SAMPLERS)}, but got {sampler!r}")
        if pruner not in PRUNERS:
            raise ConfigError(f"sweep.pruner must be one of {list(PRUNERS)}, but got {pruner!r}")
        name = sweep.get("study_name")
        return cls(
            space=str(sweep.get("space", "default")),
            n_trials=number("n_trials", int, 0),
            study_name=None if name in (None, "") else str(name),
            sampler=sampler,
            n_startup_trials=number("n_startup_trials", int, 0),
            pruner=pruner,
            pruner_startup_trials=number("pruner_startup_trials", int, 0),
            pruner_warmup_epochs=number("pruner_warmup_epochs", int, 0),
            pruner_min_epochs=number("pruner_min_epochs", int, 1) if sweep.get("pruner_min_epochs") is not None else 10,
            seed=number("seed", int, 0),
            timeout=number("timeout", float, 0, optional=True),
            heartbeat_interval=number("heartbeat_interval", float, 0.1),
            stale_after=number("stale_after", float, 1.0),
            max_failures_in_a_row=number("max_failures_in_a_row", int, 0),
            progress=bool(sweep.get("progress", True)),
            group=number("group", int, 1) if sweep.get("group") is not None else 1,
            figures=bool(sweep.get("figures", True)),
            workers=number("workers", int, 1) if sweep.get("workers") is not None else 1,
            group_shapes=flag("group_shapes", True),
        )

    def sampler_for(self, trial_index: int) -> "optuna.samplers.BaseSampler":
        """The sampler for the study's ``trial_index``-th trial (seeded per trial: resumes reproduce)."""
        import optuna

        seed = self.seed + trial_index
        if self.sampler == "random":
            return optuna.samplers.RandomSampler(seed=seed)
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=self.n_startup_trials)

    @property
    def pruned_because(self) -> str:
        """How a pruned trial's message ends: what its val.rmse was compared with."""
        if self.pruner == "halving":
            return "outside the best third of the trials that reached this epoch (successive halving)"
        return "worse than the median of earlier trials at this epoch"

    def make_pruner(self) -> "optuna.pruners.BasePruner":
        import optuna

        if self.pruner == "none":
            return optuna.pruners.NopPruner()
        if self.pruner == "halving":  # rungs at m, 3m, 9m … epochs; about a third of the trials go on at each
            return optuna.pruners.SuccessiveHalvingPruner(min_resource=self.pruner_min_epochs, reduction_factor=3)
        return optuna.pruners.MedianPruner(
            n_startup_trials=self.pruner_startup_trials, n_warmup_steps=self.pruner_warmup_epochs
        )


def shape_keys(space: SearchSpace) -> list[str]:
    """The searched keys that shape a stacked solve: those the models of a stack must share
    (:data:`physmend.ude.stacked.SHARED_KEYS`, e.g. ``train.segment_length``) and the network's width
    and depth (mixed ones are padded to the largest)."""
    from physmend.ude.stacked import SHARED_KEYS

    shaping = (*SHARED_KEYS, "ude.width", "ude.depth")
    return [key for key in space.params if any(key == s or key.startswith(s + ".") for s in shaping)]


# -- trial configs -------------------------------------------------------------------------------
def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def check_overrides(space: SearchSpace, overrides: Sequence[str]) -> None:
    """A key set on the command line must not also be searched (which one would win is unclear)."""
    both = sorted({_override_key(o) for o in overrides} & set(space.params))
    if both:
        raise ConfigError(
            f"{', '.join(both)}: set on the command line and searched by {space.label} at once; "
            "remove them from the command line or use a space that does not search them"
        )


def probe_space(space: SearchSpace, overrides: Sequence[str], config_dir: str | Path | None) -> None:
    """Compose trial configs that use every choice (numbers: their low bound), so that a key or a
    choice that does not compose fails before anything is written."""
    from physmend.config import compose

    def attempt(values: dict[str, Any]) -> str | None:
        try:
            compose([*overrides, *trial_overrides(values)], user_config_dir=config_dir)
        except ConfigError as exc:
            return str(exc)
        return None

    first = {key: p.examples()[0] for key, p in space.params.items()}
    probes = [first] + [{**first, key: v} for key, p in space.params.items() if p.kind == "choice" for v in p.choices[1:]]
    for values in probes:
        if attempt(values) is None:
            continue
        for key, value in values.items():  # find the culprit
            error = attempt({key: value})
            if error is not None:
                raise ConfigError(f"{space.label}: params.{key} = {value!r} does not compose: {error}")
        raise ConfigError(f"{space.label}: the trial {values} does not compose: {attempt(values)}")


def check_keys(space: SearchSpace, cfg: DictConfig) -> None:
    """Without overrides to compose from, every searched key must be a value in ``cfg``."""
    for key in space.params:
        node = OmegaConf.select(cfg, key, default="<missing>", throw_on_missing=False)
        if isinstance(node, str) and node == "<missing>" or isinstance(node, DictConfig):
            raise ConfigError(
                f"{space.label}: params.{key} must name a value of the composed config (run the sweep through "
                "the CLI or pass run(..., overrides=...) to search config groups)"
            )


def _touches_problem(key: str) -> bool:
    return key in ("model", "data", "simulate.dtype") or key.startswith(("model.", "data."))


class TrialConfigs:
    """Builds each trial's config and problem; the problem is shared unless a trial changes it."""

    def __init__(self, cfg: DictConfig, problem: "Problem", overrides: Sequence[str] | None, config_dir: Any) -> None:
        self.cfg = cfg
        self.overrides = None if overrides is None else list(overrides)
        self.config_dir = config_dir
        self._problems: dict[tuple[tuple[str, str], ...], Problem] = {(): problem}

    def config(self, values: dict[str, Any]) -> DictConfig:
        """The composed config of a trial: the sweep's overrides, then the trial's values."""
        if self.overrides is not None:
            from physmend.config import compose

            return compose([*self.overrides, *trial_overrides(values)], user_config_dir=self.config_dir)
        cfg = copy.deepcopy(self.cfg)
        for key, value in values.items():  # no overrides known (called from Python): patch values
            OmegaConf.update(cfg, key, value, merge=False)
        return cfg

    def problem(self, values: dict[str, Any], cfg: DictConfig) -> "Problem":
        from physmend.problem import load_problem

        key = tuple(sorted((k, hydra_value(v)) for k, v in values.items() if _touches_problem(k)))
        if key not in self._problems:
            self._problems[key] = load_problem(cfg)
        return self._problems[key]


# -- the study -----------------------------------------------------------------------------------
def open_storage(url: str) -> "optuna.storages.RDBStorage":
    """The Optuna RDB storage at ``url`` (``sqlite:///`` paths resolve against the working directory)."""
    import optuna

    from physmend.tracking import TrackingError, sqlite_path

    kwargs: dict[str, Any] = {}
    db = sqlite_path(url)
    if db is not None:
        if not db.parent.is_dir():
            raise TrackingError(f"tracking.optuna_storage {url!r}: the folder {str(db.parent)!r} for the database does not exist")
        url = f"sqlite:///{db}"
        kwargs["engine_kwargs"] = {"connect_args": {"timeout": 60}}
    try:
        return _retry(lambda: optuna.storages.RDBStorage(url, **kwargs))
    except (ImportError, ValueError, optuna.exceptions.OptunaError) as exc:
        raise TrackingError(f"tracking.optuna_storage {url!r} cannot be opened: {exc}") from None


def _retry(fn: Callable[[], Any], attempts: int = 4) -> Any:
    """Call ``fn``, retrying transient failures (two workers creating one database at once)."""
    from physmend.tracking import TrackingError

    for i in range(attempts):
        try:
            return fn()
        except (TrackingError, ImportError, KeyboardInterrupt):
            raise
        except Exception:  # noqa: BLE001 - table/migration races; re-raised on the last attempt
            if i == attempts - 1:
                raise
            time.sleep(0.5 + 0.5 * i + (os.getpid() % 7) / 10)
    raise AssertionError("unreachable")


def study_fingerprint(cfg: DictConfig, space: SearchSpace) -> dict[str, Any]:
    """What a study was started with: the config values that shape trials (``_COMPARED``), and the space.

    ``sweep.*`` settings (n_trials, sampler, pruner, timeout …) may change when resuming.
    """
    data = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(data, dict)
    keep = {k: data[k] for k in _COMPARED if k in data}
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            flat[prefix] = node

    walk("", keep)
    return {"config": flat, "space": space.spec()}


def check_fingerprint(study_name: str, stored: dict[str, Any] | None, current: dict[str, Any]) -> None:
    """Resuming a study with another configuration would mix incomparable trials: refuse."""
    if not stored:
        return
    old, new = stored.get("config", {}), current["config"]
    diffs = [f"{k}: {old.get(k, '<unset>')!r} -> {new.get(k, '<unset>')!r}" for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if stored.get("space") != current["space"]:
        diffs.append("the search space changed")
    if diffs:
        shown = "; ".join(diffs[:6]) + (f"; … ({len(diffs) - 6} more)" if len(diffs) > 6 else "")
        raise ConfigError(
            f"study {study_name!r} was started with another configuration ({shown}); rerun the original command "
            "to resume it, or pass sweep.study_name=NEW_NAME to start a new study"
        )


def default_study_name(problem: "Problem", cfg: DictConfig, space: SearchSpace) -> str:
    """``<model>-<data>-<space>``."""
    return f"{problem.model.name}-{cfg.data.name}-{space.name}"


def _open_study(storage: Any, name: str, settings: Settings) -> tuple["optuna.Study", bool]:
    """``(study, created)``: create the study, or load it if it exists (exactly one creator wins)."""
    import optuna

    try:
        study = optuna.create_study(storage=storage, study_name=name, direction="minimize", pruner=settings.make_pruner())
        return study, True
    except optuna.exceptions.DuplicatedStudyError:
        return optuna.load_study(study_name=name, storage=storage, pruner=settings.make_pruner()), False


@dataclass
class Tally:
    """Trials of a study by what they mean for ``n_trials``."""

    complete: int = 0
    pruned: int = 0
    failed: int = 0
    running: int = 0
    uncounted: int = 0
    best_value: float | None = None
    best_number: int | None = None

    @property
    def counted(self) -> int:
        """Trials that reached a verdict (COMPLETE, PRUNED, FAIL other than interrupted/surplus)."""
        return self.complete + self.pruned + self.failed


def _uncounted(t: Any) -> bool:
    from optuna.trial import TrialState

    return t.state == TrialState.FAIL and t.user_attrs.get(REASON_ATTR) in UNCOUNTED


def tally(trials: Sequence[Any]) -> Tally:
    """Count ``trials`` (FrozenTrials) and find the best complete one."""
    from optuna.trial import TrialState

    out = Tally()
    for t in trials:
        if t.state == TrialState.COMPLETE:
            out.complete += 1
            if t.value is not None and (out.best_value is None or t.value < out.best_value):
                out.best_value, out.best_number = t.value, t.number
        elif t.state == TrialState.PRUNED:
            out.pruned += 1
        elif t.state == TrialState.RUNNING:
            out.running += 1
        elif t.state == TrialState.FAIL:
            if _uncounted(t):
                out.uncounted += 1
            else:
                out.failed += 1
    return out


# -- workers, heartbeats, stale trials -----------------------------------------------------------
def _worker() -> dict[str, Any]:
    return {"host": socket.gethostname(), "pid": os.getpid()}


def _pid_alive(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, ValueError, TypeError, OverflowError):
        return True  # exists but not ours, or unknown: let the heartbeat decide
    return True


def is_stale(trial: Any, *, now: float, stale_after: float, me: dict[str, Any]) -> bool:
    """Whether a RUNNING trial's worker is gone (see the module docstring)."""
    worker = trial.user_attrs.get(WORKER_ATTR) or {}
    if worker.get("host") == me["host"]:
        if worker.get("pid") == me["pid"] or not _pid_alive(worker.get("pid")):
            return True  # this process runs no trial while it looks; a dead PID runs none either
    beat = trial.user_attrs.get(HEARTBEAT_ATTR)
    if beat is None and trial.datetime_start is not None:
        beat = trial.datetime_start.timestamp()
    return beat is not None and now - float(beat) > stale_after


class Heartbeat:
    """Context manager: record ``time.time()`` on a trial every ``interval`` s from a thread."""

    def __init__(self, trial: "optuna.Trial", interval: float) -> None:
        self.trial, self.interval = trial, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name="physmend-heartbeat", daemon=True)

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.trial.set_user_attr(HEARTBEAT_ATTR, time.time())
            except Exception:  # noqa: BLE001 - a missed beat is harmless; the next one retries
                pass

    def __enter__(self) -> Heartbeat:
        self.trial.set_user_attr(HEARTBEAT_ATTR, time.time())
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


# -- one sweep -----------------------------------------------------------------------------------
@dataclass
class Outcome:
    """How one trial ended."""

    number: int
    state: str  # COMPLETE | PRUNED | FAIL
    value: float | None = None
    run_id: str | None = None
    reason: str = ""


@dataclass
class Sweep:
    """Everything one worker process needs to run trials of a study."""

    cfg: DictConfig
    settings: Settings
    space: SearchSpace
    study: Any
    storage: Any
    store: "Store"
    parent_run_id: str
    configs: TrialConfigs
    train: Callable[..., Any]
    me: dict[str, Any] = field(default_factory=_worker)
    failures_in_a_row: int = 0

    # ---- the loop
    def loop(self, bar: Any) -> list[Outcome]:
        """Ask, train and tell until the study has ``n_trials`` trials or time runs out."""
        start = time.monotonic()
        outcomes: list[Outcome] = []
        while True:
            self.fail_stale_trials(bar)
            counts = tally(self.study.get_trials(deepcopy=False))
            _show(bar, counts)
            if counts.counted + counts.running >= self.settings.n_trials:
                break
            if self.settings.timeout is not None and time.monotonic() - start >= self.settings.timeout:
                _say(bar, f"sweep.timeout of {self.settings.timeout:g} s reached; no new trial is started")
                break
            if self.settings.group > 1:
                batch = self.trial_group(bar, self.group_size(counts))
                if batch is None:
                    break
                for outcome in batch:
                    outcomes.append(outcome)
                    self._after(outcome, bar)
                continue
            outcome = self.one_trial(bar)
            if outcome is None:
                break
            outcomes.append(outcome)
            self._after(outcome, bar)
        return outcomes

    def group_size(self, counts: Tally) -> int:
        """Trials to ask together: ``sweep.group``, but while fewer than ``pruner_startup_trials``
        trials are complete only the missing ones: the median pruner has nothing to compare with
        yet, so a first group would otherwise train every one of its trials to the end."""
        size = min(self.settings.group, self.settings.n_trials - counts.counted - counts.running)
        missing = self.settings.pruner_startup_trials - counts.complete
        if self.settings.pruner == "median" and missing > 0:  # halving compares trials from the first one on
            size = min(size, missing)
        return max(1, size)

    def trial_group(self, bar: Any, size: int) -> list[Outcome] | None:
        """Ask for up to ``size`` trials and train those that can share a solve as one stack
        (:func:`physmend.ude.stacked.train_stack`, grouped by ``stack_key``); each is still its own
        trial with its own child run. ``None`` when no trial could be asked (surplus).

        With ``sweep.group_shapes`` the sampler proposes the first trial's :func:`shape_keys` freely
        and the others' with those values fixed (Optuna's ``PartialFixedSampler``): the group is one
        stack of same-shaped networks (no padding) instead of several stacks solved one after another.
        """
        import optuna
        from optuna.trial import TrialState

        from physmend.ude.stacked import stack_key

        trials: list[Any] = []
        first: dict[int, dict[str, Any]] = {}  # the values of a trial suggested before the others are asked
        shared: dict[str, Any] = {}  # group_shapes: the first trial's shape, which the others take
        for _ in range(max(1, size)):
            sampler = self.settings.sampler_for(len(self.study.get_trials(deepcopy=False)))
            if shared:
                with warnings.catch_warnings():  # PartialFixedSampler is "experimental" since optuna 2.4
                    warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                    sampler = optuna.samplers.PartialFixedSampler(shared, sampler)
            self.study.sampler = sampler
            trial = self.study.ask()
            trial.set_user_attr(WORKER_ATTR, self.me)
            if self._surplus(trial):
                trial.set_user_attr(REASON_ATTR, "surplus")
                self.study.tell(trial, state=TrialState.FAIL)
                break
            trials.append(trial)
            if self.settings.group_shapes and not trials[1:]:
                first[trial.number] = self.space.suggest(trial)
                shared = {key: first[trial.number][key] for key in shape_keys(self.space)}
        if not trials:
            return None
        # the others are suggested once the whole group is asked (the order of earlier versions: a
        # study repeated with the same seed proposes the same trials)
        asked = [(trial, first[trial.number] if trial.number in first else self.space.suggest(trial)) for trial in trials]
        outcomes: dict[int, Outcome] = {}
        groups: dict[Any, list[tuple[Any, dict[str, Any], DictConfig, Any]]] = {}
        for trial, values in asked:
            try:
                cfg = self.configs.config(values)
                problem = self.configs.problem(values, cfg)
            except Exception as exc:  # noqa: BLE001 - a bad trial config fails the trial, not the sweep
                outcomes[trial.number] = Outcome(trial.number, "FAIL", reason=f"{type(exc).__name__}: {exc}")
                continue
            groups.setdefault((stack_key(cfg), id(problem)), []).append((trial, values, cfg, problem))
        try:
            with contextlib.ExitStack() as beats:
                for trial, _ in asked:
                    beats.enter_context(Heartbeat(trial, self.settings.heartbeat_interval))
                for members in groups.values():
                    outcomes.update(self._train_group(members))
        except KeyboardInterrupt:
            for trial, _ in asked:
                if trial.number not in outcomes:
                    trial.set_user_attr(REASON_ATTR, "interrupted")
                    self.study.tell(trial, state=TrialState.FAIL)
            raise
        for trial, _ in asked:
            self.tell(trial, outcomes[trial.number])
        return [outcomes[t.number] for t, _ in asked]

    def _train_group(self, members: list[tuple[Any, dict[str, Any], DictConfig, Any]]) -> dict[int, Outcome]:
        """Train one stack; then log each trial's buffered metrics and result to its own child run."""
        from physmend.ude.stacked import train_stack

        reporters = [Reporter(trial, None, self.settings.pruned_because) for trial, *_ in members]
        try:
            results: list[Any] = train_stack([cfg for _, _, cfg, _ in members], members[0][3],
                                             report=lambda i, epoch, row: reporters[i](epoch, row),
                                             final_eval="batched", figures=self.settings.figures)
        except Exception as exc:  # noqa: BLE001 - the whole stack failed: every trial FAILs, the sweep goes on
            results = [exc] * len(members)
        out: dict[int, Outcome] = {}
        for (trial, values, cfg, _), reporter, result in zip(members, reporters, results):
            holder: dict[str, str] = {}
            try:
                out[trial.number] = self._log_stacked(trial, values, cfg, reporter, result, holder)
            except Exception as exc:  # noqa: BLE001 - diverged, solver failure, anything: FAIL
                self._mark_child(holder.get("run_id"), "FAIL")
                out[trial.number] = Outcome(trial.number, "FAIL", run_id=holder.get("run_id"),
                                            reason=f"{type(exc).__name__}: {exc}")
        return out

    def _log_stacked(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, reporter: "Reporter",
                     result: Any, holder: dict[str, str]) -> Outcome:
        import mlflow
        import optuna

        from physmend.tracking import selection as sel

        with self._child_run(trial, values, cfg, holder, {"physmend.stacked": "true"}) as run_:
            for epoch, metrics in reporter.buffered:
                run_.log_metrics(metrics, step=epoch)
            if isinstance(result, optuna.TrialPruned):
                run_.set_tags({sel.TRIAL_STATE_TAG: "PRUNED", "physmend.pruned": str(result) or "pruned"})
                mlflow.end_run("KILLED")
                return Outcome(trial.number, "PRUNED", value=reporter.last_value, run_id=run_.run_id, reason=str(result))
            if isinstance(result, BaseException):
                raise result
            value = float(result.val_rmse)
            if not math.isfinite(value):
                raise FloatingPointError(f"the final val.rmse is not finite ({value})")
            _log_result(run_, result, step=reporter.last_epoch + 1, figures=self.settings.figures)
            run_.set_tags({sel.TRIAL_STATE_TAG: "COMPLETE"})
        return Outcome(trial.number, "COMPLETE", value=value, run_id=run_.run_id)

    def _after(self, outcome: Outcome, bar: Any) -> None:
        if outcome.state == "FAIL":
            _say(bar, f"trial {outcome.number} failed: {outcome.reason}")
            self.failures_in_a_row += 1
            limit = self.settings.max_failures_in_a_row
            if limit and self.failures_in_a_row >= limit:
                raise ConfigError(
                    f"{self.failures_in_a_row} trials in a row failed (sweep.max_failures_in_a_row = {limit}); "
                    f"the last: trial {outcome.number}: {outcome.reason}. Check the configuration and the search "
                    f"space {self.space.label}; resume with the same command"
                )
        else:
            self.failures_in_a_row = 0

    def one_trial(self, bar: Any) -> Outcome | None:
        """Ask for one trial and run it; ``None`` when the trial turned out to be surplus."""
        from optuna.trial import TrialState

        n_before = len(self.study.get_trials(deepcopy=False))
        self.study.sampler = self.settings.sampler_for(n_before)
        trial = self.study.ask()
        trial.set_user_attr(WORKER_ATTR, self.me)
        if self._surplus(trial):
            trial.set_user_attr(REASON_ATTR, "surplus")
            self.study.tell(trial, state=TrialState.FAIL)
            return None
        try:
            with Heartbeat(trial, self.settings.heartbeat_interval):
                outcome = self.run_trial(trial)
        except KeyboardInterrupt:
            trial.set_user_attr(REASON_ATTR, "interrupted")
            self.study.tell(trial, state=TrialState.FAIL)
            raise
        self.tell(trial, outcome)
        return outcome

    def _surplus(self, trial: "optuna.Trial") -> bool:
        """Whether trials numbered before this one already fill ``n_trials`` (a race between workers)."""
        from optuna.trial import TrialState

        ahead = [
            t for t in self.study.get_trials(deepcopy=False)
            if t.number < trial.number and (t.state == TrialState.RUNNING or (t.state.is_finished() and not _uncounted(t)))
        ]
        return len(ahead) >= self.settings.n_trials

    def tell(self, trial: "optuna.Trial", outcome: Outcome) -> None:
        from optuna.trial import TrialState

        try:
            if outcome.state == "COMPLETE":
                self.study.tell(trial, outcome.value)
            elif outcome.state == "PRUNED":
                self.study.tell(trial, state=TrialState.PRUNED)
            else:
                trial.set_user_attr(REASON_ATTR, outcome.reason[:2000])
                self.study.tell(trial, state=TrialState.FAIL)
        except (ValueError, RuntimeError) as exc:  # finished meanwhile, e.g. judged stale by another worker
            sys.stderr.write(f"trial {trial.number}: could not record the result in the study: {exc}\n")

    # ---- one trial
    def run_trial(self, trial: "optuna.Trial") -> Outcome:
        """Compose, train and log one trial as a child run; exceptions from training become FAIL."""
        values = self.space.suggest(trial)
        try:
            cfg = self.configs.config(values)
            problem = self.configs.problem(values, cfg)
        except Exception as exc:  # noqa: BLE001 - a bad trial config fails the trial, not the sweep
            return Outcome(trial.number, "FAIL", reason=f"{type(exc).__name__}: {exc}")
        holder: dict[str, str] = {}
        try:
            return self._train_logged(trial, values, cfg, problem, holder)
        except Exception as exc:  # noqa: BLE001 - diverged, solver failure, anything: FAIL, sweep goes on
            self._mark_child(holder.get("run_id"), "FAIL")
            return Outcome(trial.number, "FAIL", run_id=holder.get("run_id"), reason=f"{type(exc).__name__}: {exc}")
        except KeyboardInterrupt:
            self._mark_child(holder.get("run_id"), "FAIL", error="interrupted (KeyboardInterrupt)")
            raise

    @contextlib.contextmanager
    def _child_run(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, holder: dict[str, str],
                   extra_tags: dict[str, str] | None = None) -> Iterator[Any]:
        """The trial's child run under the sweep's parent, its ID recorded in ``holder`` and the trial."""
        from physmend.tracking import stage_run
        from physmend.tracking import selection as sel

        tags = {sel.STUDY_TAG: self.study.study_name, sel.TRIAL_NUMBER_TAG: str(trial.number), **(extra_tags or {})}
        with stage_run(
            self.store, cfg, stage=sel.TRIAL_STAGE, source_run_id=self.parent_run_id,
            run_name=f"trial-{trial.number:04d}", parent_run_id=self.parent_run_id, tags=tags,
        ) as run_:
            holder["run_id"] = run_.run_id
            trial.set_user_attr(RUN_ID_ATTR, run_.run_id)
            run_.log_params(values)
            yield run_

    def _train_logged(self, trial: "optuna.Trial", values: dict[str, Any], cfg: DictConfig, problem: "Problem", holder: dict[str, str]) -> Outcome:
        import mlflow
        import optuna

        from physmend.tracking import selection as sel

        with self._child_run(trial, values, cfg, holder) as run_:
            reporter = Reporter(trial, run_, self.settings.pruned_because)
            try:
                result = self.train(cfg, problem, report=reporter)
            except optuna.TrialPruned as exc:
                run_.set_tags({sel.TRIAL_STATE_TAG: "PRUNED", "physmend.pruned": str(exc) or "pruned"})
                mlflow.end_run("KILLED")
                return Outcome(trial.number, "PRUNED", value=reporter.last_value, run_id=run_.run_id, reason=str(exc))
            value = float(result.val_rmse)
            if not math.isfinite(value):
                raise FloatingPointError(f"the final val.rmse is not finite ({value})")
            _log_result(run_, result, step=reporter.last_epoch + 1, figures=self.settings.figures)
            run_.set_tags({sel.TRIAL_STATE_TAG: "COMPLETE"})
        return Outcome(trial.number, "COMPLETE", value=value, run_id=run_.run_id)

    def _mark_child(self, run_id: str | None, state: str, *, error: str | None = None) -> None:
        from physmend.tracking import ERROR_TAG
        from physmend.tracking import selection as sel

        if run_id is None:
            return
        try:
            self.store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, state)
            if error:
                self.store.client.set_tag(run_id, ERROR_TAG, error)
        except Exception:  # noqa: BLE001 - the trial's FAIL in the study is what counts
            pass

    # ---- stale trials
    def fail_stale_trials(self, bar: Any) -> None:
        """Mark RUNNING trials whose worker is gone FAIL (interrupted), their child runs KILLED."""
        from optuna.trial import TrialState

        now = time.time()
        for t in self.study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            if not is_stale(t, now=now, stale_after=self.settings.stale_after, me=self.me):
                continue
            worker = t.user_attrs.get(WORKER_ATTR) or {}
            try:
                trial_id = self.storage.get_trial_id_from_study_id_trial_number(
                    self.storage.get_study_id_from_name(self.study.study_name), t.number
                )
                self.storage.set_trial_user_attr(trial_id, REASON_ATTR, "interrupted")
                self.study.tell(t.number, state=TrialState.FAIL)
            except Exception:  # noqa: BLE001 - another worker got there first
                continue
            where = f"{worker.get('host', '?')}:{worker.get('pid', '?')}"
            self._kill_child(t.user_attrs.get(RUN_ID_ATTR), f"interrupted: its worker {where} stopped")
            _say(bar, f"trial {t.number} was left running by worker {where}, which stopped; marked FAIL (interrupted)")

    def _kill_child(self, run_id: str | None, reason: str) -> None:
        from physmend.tracking import ERROR_TAG
        from physmend.tracking import selection as sel

        if not run_id:
            return
        try:
            run = self.store.client.get_run(run_id)
            self.store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, "FAIL")
            if run.info.status == "RUNNING":
                self.store.client.set_tag(run_id, ERROR_TAG, reason)
                self.store.client.set_terminated(run_id, "KILLED")
        except Exception:  # noqa: BLE001 - the run may be gone; the study is the record
            pass


class Reporter:
    """The ``report`` callback of one trial: per-epoch metrics to MLflow, pruning via Optuna."""

    def __init__(self, trial: "optuna.Trial", run_: Any, because: str) -> None:
        """``run_`` None: metrics are kept in ``buffered`` (a stacked trial's run is written afterwards);
        ``because``: how the pruner compares (:attr:`Settings.pruned_because`, ends a pruned trial's message)."""
        self.trial, self.run_, self.because = trial, run_, because
        self.last_epoch = 0
        self.last_value: float | None = None
        self.buffered: list[tuple[int, dict[str, float]]] = []

    def __call__(self, epoch: int, metrics: dict[str, float]) -> None:
        import optuna

        epoch = int(epoch)
        self.last_epoch = max(self.last_epoch, epoch)
        finite = {k: float(v) for k, v in metrics.items() if k != "epoch" and v is not None and math.isfinite(float(v))}
        if self.run_ is None:
            self.buffered.append((epoch, finite))
        else:
            self.run_.log_metrics(finite, step=epoch)
        value = finite.get("val.rmse")
        if value is None:
            return
        self.last_value = value
        self.trial.report(value, epoch)
        if self.trial.should_prune():
            raise optuna.TrialPruned(f"pruned at epoch {epoch}: val.rmse {value:.4g} is {self.because}")


def _log_result(run_: Any, result: Any, *, step: int, figures: bool = True) -> None:
    """Final metrics (at ``step``, after the per-epoch ones), model files, history, figures (``figures``)."""
    import matplotlib.pyplot as plt
    import mlflow

    metrics = {k: float(v) for k, v in result.metrics.items() if v is not None and math.isfinite(float(v))}
    metrics["val.rmse"] = float(result.val_rmse)
    run_.log_metrics(metrics, step=step)
    with tempfile.TemporaryDirectory(prefix="physmend-artifacts-") as tmp:
        for rel, content in result.artifacts.items():
            path = Path(tmp) / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, bytes):
                path.write_bytes(content)
            else:
                path.write_text(content)
        if result.artifacts:
            mlflow.log_artifacts(tmp)
    run_.log_json(result.history, "history.json")
    for rel, fig in (result.figures or {}).items():
        if figures:
            run_.log_figure(fig, rel)
        plt.close(fig)


def _say(bar: Any, message: str) -> None:
    """A line on stderr above the progress bar."""
    bar.write(message, file=sys.stderr)


def _show(bar: Any, counts: Tally) -> None:
    bar.n = min(counts.counted, bar.total) if bar.total else counts.counted
    if counts.best_value is not None:
        bar.set_postfix_str(f"best val.rmse {counts.best_value:.4g} (trial {counts.best_number})", refresh=False)
    bar.refresh()


# -- parent run ----------------------------------------------------------------------------------
def _parent_tags(cfg: DictConfig, space: SearchSpace, study_name: str, storage_url: str, source_run_id: str | None) -> dict[str, str]:
    from physmend.tracking import DATA_TAG, MODEL_TAG, SOURCE_TAG, STAGE_TAG
    from physmend.tracking import selection as sel

    return {
        STAGE_TAG: STAGE,
        SOURCE_TAG: source_run_id or "",
        MODEL_TAG: str(OmegaConf.select(cfg, "model.builder", default="")),
        DATA_TAG: str(OmegaConf.select(cfg, "data.name", default="")),
        sel.STUDY_TAG: study_name,
        sel.SPACE_TAG: space.name if space.label.startswith("sweeps/") else space.label,
        sel.STORAGE_TAG: storage_url,
    }


def _create_parent(store: "Store", cfg: DictConfig, space: SearchSpace, settings: Settings, tags: dict[str, str]) -> str:
    import yaml

    run = store.client.create_run(store.experiment_id, run_name=f"sweep-{tags['physmend.study']}", tags=tags)
    run_id = run.info.run_id
    store.client.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
    store.client.log_text(run_id, yaml.safe_dump(space.spec(), sort_keys=False), "space.yaml")
    for key, value in {"space": tags["physmend.space"], "sampler": settings.sampler, "pruner": settings.pruner,
                       "seed": settings.seed, "study": tags["physmend.study"]}.items():
        store.client.log_param(run_id, key, str(value))
    return run_id


def _parent_run(study: Any, created: bool, store: "Store", make: Callable[[], str]) -> str:
    """The sweep's parent run ID: created by the study's creator, looked up (and resumed) by others."""
    from physmend.tracking import TrackingError

    if created:
        run_id = make()
        study.set_user_attr(PARENT_ATTR, run_id)
        return run_id
    deadline = time.monotonic() + PARENT_WAIT_S
    run_id = study.user_attrs.get(PARENT_ATTR)
    while run_id is None and time.monotonic() < deadline:  # the creator is writing it right now
        time.sleep(0.5)
        run_id = study.user_attrs.get(PARENT_ATTR)
    if run_id is None:  # the creator died before writing it
        run_id = make()
        study.set_user_attr(PARENT_ATTR, run_id)
        return run_id
    try:
        run = store.client.get_run(run_id)
    except Exception:  # noqa: BLE001 - MlflowException: not in this store
        run = None
    if run is None or run.info.lifecycle_stage != "active" or run.info.experiment_id != store.experiment_id:
        raise TrackingError(
            f"study {study.study_name!r} belongs to sweep run {run_id!r}, which is not an active run of experiment "
            f"{store.experiment_name!r} in {store.uri}; pass sweep.study_name=NEW_NAME to start a new study"
        )
    if run.info.status != "RUNNING":
        store.client.update_run(run_id, status="RUNNING")
    return run_id


def _finish_parent(sweep: Sweep, status: str) -> Tally:
    """Record counts and the best trial on the parent; end it when no other worker still runs trials."""
    from physmend.tracking import selection as sel

    client = sweep.store.client
    trials = sweep.study.get_trials(deepcopy=False)
    counts = tally(trials)
    parent = sweep.parent_run_id
    metrics = {"trials.complete": counts.complete, "trials.pruned": counts.pruned,
               "trials.failed": counts.failed, "trials.interrupted": counts.uncounted}
    if counts.best_value is not None:
        metrics["best.val.rmse"] = counts.best_value
        best = next(t for t in trials if t.number == counts.best_number)
        best_run = best.user_attrs.get(RUN_ID_ATTR)
        if best_run:
            sel.record_auto_selection(sweep.store, parent, best_run)
    ts = int(time.time() * 1000)
    from mlflow.entities import Metric

    client.log_batch(parent, metrics=[Metric(k, float(v), ts, 0) for k, v in metrics.items()])
    client.set_tag(parent, "physmend.n_trials", str(sweep.settings.n_trials))
    if counts.running == 0:  # otherwise the last worker to finish ends it
        client.set_terminated(parent, status)
    return counts


# -- entry point ---------------------------------------------------------------------------------
def _trainer() -> Callable[..., Any]:
    from physmend.ude import train

    return train


def run(
    cfg: DictConfig,
    source_run_id: str | None = None,
    *,
    overrides: Sequence[str] | None = None,
    config_dir: str | Path | None = None,
    given_wins: bool = False,
) -> str:
    """Run (or resume, or join as a worker) the sweep configured by ``cfg.sweep``; returns the parent run ID.

    ``overrides``/``config_dir`` are what ``cfg`` was composed from (the CLI passes them): each
    trial's config is composed from them plus the trial's values. Without them (a call from
    Python), the trial's values are patched into a copy of ``cfg``. A key both given in ``overrides``
    and searched by the space is an error, or with ``given_wins`` (``physmend discover``, whose user did
    not pick the space) no longer searched, said in one line.

    Everything the user gave (space, settings, model, data, source run) is checked before any run
    is written. A diverging trial is recorded FAIL and the sweep goes on; Ctrl-C records the
    running trial FAIL (its run KILLED) and re-raises ``KeyboardInterrupt``.
    """
    from physmend.problem import load_problem
    from physmend.tracking import get_run, open_store

    settings = Settings.from_cfg(cfg.sweep)
    if settings.workers > 1 and overrides is None:
        raise ConfigError(f"sweep.workers={settings.workers} starts worker processes from the command line "
                          "(physmend sweep … sweep.workers=N); from Python, start several processes with the same "
                          "configuration yourself (they share the study)")
    space = load_space(settings.space)
    if overrides is not None and given_wins:
        both = sorted({_override_key(o) for o in overrides} & set(space.params))
        if both:
            print(f"sweep: {', '.join(both)} given on the command line: {space.label} does not search "
                  f"{'it' if len(both) == 1 else 'them'} in this sweep")
            space = space.without(both)
    if overrides is not None:
        check_overrides(space, overrides)
        probe_space(space, overrides, config_dir)
    else:
        check_keys(space, cfg)
    problem = load_problem(cfg)
    storage = open_storage(str(cfg.tracking.optuna_storage))
    store = _retry(lambda: open_store(cfg.tracking))
    if source_run_id:
        get_run(store, source_run_id)
    study_name = settings.study_name or default_study_name(problem, cfg, space)
    study, created = _study(storage, study_name, settings, space, study_fingerprint(cfg, space))
    tags = _parent_tags(cfg, space, study_name, storage.url, source_run_id)
    parent = _parent_run(study, created, store, lambda: _create_parent(store, cfg, space, settings, tags))
    configs = TrialConfigs(cfg, problem, overrides, config_dir)
    helpers = _start_workers(settings.workers - 1, source_run_id, overrides or [], config_dir)
    return _drive(Sweep(cfg, settings, space, study, storage, store, parent, configs, _trainer()), helpers)


def _start_workers(count: int, source_run_id: str | None, overrides: Sequence[str], config_dir: str | Path | None) -> list[Any]:
    """``count`` more ``physmend sweep`` processes on the same study (one torch thread each), started
    after this one has created the study and its parent run."""
    if count < 1:
        return []
    cmd = [sys.executable, "-m", "physmend.cli", "sweep", *([source_run_id] if source_run_id else []),
           *(["--config-dir", str(config_dir)] if config_dir is not None else []),
           *overrides, "sweep.workers=1", "sweep.progress=false"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    return [subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL) for _ in range(count)]


def _join_workers(helpers: list[Any]) -> None:
    """Wait for the worker processes; say which ended with an error (their stderr is the user's)."""
    for proc in helpers:
        rc = proc.wait()
        if rc != 0:
            sys.stderr.write(f"sweep worker process {proc.pid} ended with exit status {rc}\n")


def _study(storage: Any, name: str, settings: Settings, space: SearchSpace, fingerprint: dict[str, Any]) -> tuple[Any, bool]:
    """Create the study (recording what it was started with, enqueuing ``first_trials``) or load and check it."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study, created = _retry(lambda: _open_study(storage, name, settings))
    if created:
        study.set_user_attr(CONFIG_ATTR, fingerprint)
        for values in space.first_trials:
            study.enqueue_trial(values, skip_if_exists=True)
    else:
        check_fingerprint(name, study.user_attrs.get(CONFIG_ATTR), fingerprint)
    return study, created


def _drive(sweep: Sweep, helpers: Sequence[Any] = ()) -> str:
    """Run this worker's loop, then wait for the ``helpers`` (worker processes) before the summary."""
    from tqdm import tqdm

    bar = tqdm(total=sweep.settings.n_trials, desc=f"sweep {sweep.study.study_name}", unit="trial",
               file=sys.stderr, disable=not sweep.settings.progress, dynamic_ncols=True)
    status = "FINISHED"
    try:
        sweep.loop(bar)
        _join_workers(list(helpers))
    except KeyboardInterrupt:
        status = "KILLED"
        _say(bar, "interrupted: the running trial is recorded FAIL (interrupted); rerun the same command to resume")
        for proc in helpers:  # a Ctrl-C reaches them too: they record their own running trials
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:  # only this process was interrupted: pass it on
                proc.send_signal(signal.SIGINT)
                proc.wait()
        raise
    except BaseException as exc:
        status = "FAILED"
        for proc in helpers:  # their running trials are marked FAIL (interrupted) once their heartbeats go stale
            proc.terminate()
        from physmend.tracking import ERROR_TAG

        sweep.store.client.set_tag(sweep.parent_run_id, ERROR_TAG, f"{type(exc).__name__}: {exc}"[:5000])
        raise
    finally:
        bar.close()
        if status == "FINISHED":
            print(summary(sweep, _finish_parent(sweep, status)))
        else:
            try:
                _finish_parent(sweep, status)
            except Exception as exc:  # noqa: BLE001 - never mask the error that ended the sweep
                sys.stderr.write(f"could not record the end of sweep run {sweep.parent_run_id}: {exc}\n")
    return sweep.parent_run_id


def summary(sweep: Sweep, counts: Tally) -> str:
    """What the sweep found and the exact next commands."""
    from physmend.tracking import selection as sel

    parent = sweep.store.client.get_run(sweep.parent_run_id)
    tags = parent.data.tags
    lines = [
        f"sweep {sweep.study.study_name} (space {sweep.space.label}), run {sweep.parent_run_id}:",
        f"  {counts.counted} of {sweep.settings.n_trials} trials: {counts.complete} complete, {counts.pruned} pruned, "
        f"{counts.failed} failed" + (f" ({counts.uncounted} interrupted, not counted)" if counts.uncounted else "")
        + (f"; {counts.running} still running in other workers" if counts.running else ""),
    ]
    best = tags.get(sel.BEST_TAG)
    if best is None or counts.best_value is None:
        lines += ["  no trial finished training, so nothing is selected.",
                  "next: look at the failures with `physmend runs`, then change the configuration or the search space"]
        return "\n".join(lines)
    frozen = next(t for t in sweep.study.get_trials(deepcopy=False) if t.number == counts.best_number)
    params = " ".join(f"{k}={hydra_value(v)}" for k, v in frozen.params.items())
    lines.append(f"  best: trial {counts.best_number}, val.rmse {counts.best_value:.6g}, run {best}")
    lines.append(f"        {params}")
    selected, by = tags.get(sel.SELECTED_TAG), tags.get(sel.SELECTED_BY_TAG)
    if selected == best:
        lines.append(f"  selected: {selected} (automatic: lowest val.rmse)")
    else:
        lines.append(f"  selected: {selected} (chosen by {by}; kept — `physmend select {best}` takes the best)")
    lines += [
        "next:",
        "  physmend runs                  # every trial, the selection marked",
        "  physmend select RUN_ID         # choose another trial",
        "  physmend mask                  # keep only the corrections that matter (on the selected trial)",
    ]
    return "\n".join(lines)


