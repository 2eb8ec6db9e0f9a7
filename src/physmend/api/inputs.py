"""What a Python caller hands the API, turned into what the command line would have composed.

``model``, ``data`` and settings become Hydra overrides plus (where the model or data live in
memory) a private config directory, so that a stage run from Python is composed, checked and run
exactly as ``physmend STAGE [--config-dir D] key=value …`` would be. In-memory telemetry
(:class:`Experiment` tables) is checked first and only then written, as the CSV files and data
config that :mod:`physmend.data` reads, into a temporary folder that lives as long as the results
made from it (a later stage called with one of those results reuses it).
"""

from __future__ import annotations

import re
import shutil
import tempfile
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from physmend.config import ConfigError
from physmend.data import DataError
from physmend.data.config import ROLES

#: the option name of the model and data configs written for a call (``model=physmend_api`` …)
OPTION = "physmend_api"
_SAFE = re.compile(r"[^\w.-]")


@dataclass(frozen=True)
class Experiment:
    """One recorded experiment given as a table.

    Attributes:
        frame: a pandas DataFrame, shape ``(n_samples, 1 + n_channels)``: the time column (in
            ``time_unit``, seconds unless declared) and one column per measured output or recorded
            input, named as in the model (NaN: not measured at that time).
        role: ``"train"``, ``"validation"`` or ``"test"``.
        parameters: model parameter name -> value for this experiment (model units).
        initial: state name -> known initial value, or ``[low, high]`` for an unknown one.
        id: the experiment's name (default: its position, ``"1"``, ``"2"`` …).
    """

    frame: Any
    role: str | None = "train"
    parameters: Mapping[str, float] = field(default_factory=dict)
    initial: Mapping[str, Any] = field(default_factory=dict)
    id: str | None = None


@dataclass(frozen=True)
class Dataset:
    """Experiments given as tables plus what the data config would say about all of them.

    ``time_column``: the name of the time column in every table; ``time_unit``: ``s`` or the model's
    own time unit; ``columns``: model name -> column name where they differ.
    """

    experiments: Sequence[Experiment]
    name: str = "api"
    time_column: str = "time"
    time_unit: str | None = None
    columns: Mapping[str, str] = field(default_factory=dict)
    validation_fraction: float | None = None


class Workspace:
    """A temporary folder (config directory and telemetry) removed when no result refers to it."""

    def __init__(self) -> None:
        self.path = Path(tempfile.mkdtemp(prefix="physmend-api-"))
        self.parent: Workspace | None = None
        self._cleanup = weakref.finalize(self, shutil.rmtree, str(self.path), True)

    @property
    def conf(self) -> Path:
        return self.path / "conf"

    def remove(self) -> None:
        self._cleanup()


@dataclass(frozen=True)
class Inputs:
    """What one API call composes from: Hydra ``overrides`` and the config directory searched first
    (``None``: the shipped and bundled configs only), plus the workspace that must outlive the runs."""

    overrides: tuple[str, ...] = ()
    config_dir: str | None = None
    workspace: Workspace | None = field(default=None, compare=False, repr=False)

    def with_settings(self, extra: Sequence[str]) -> Inputs:
        """These inputs with ``extra`` overrides, which replace any earlier override of the same key."""
        keys = {_key(o) for o in extra}
        kept = tuple(o for o in self.overrides if _key(o) not in keys)
        return Inputs((*kept, *extra), self.config_dir, self.workspace)


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


# -- settings -------------------------------------------------------------------------------------------

def hydra_text(value: Any) -> str:
    """``value`` written as a Hydra override value: scalars as the sweep writes them, lists ``[a,b]``,
    mappings ``{k: v}``."""
    from physmend.sweep.space import hydra_value

    if isinstance(value, Mapping):
        return "{" + ", ".join(f"{hydra_text(str(k))}: {hydra_text(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_text(v) for v in value) + "]"
    if isinstance(value, Path):
        value = str(value)
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):  # a numpy scalar
        value = value.item()
    return hydra_value(value)


def setting_overrides(settings: Mapping[str, Any], overrides: Sequence[str] | str = ()) -> list[str]:
    """Keyword settings (``sweep={"n_trials": 4}``, ``**{"sweep.n_trials": 4}``, ``seed=1``) and
    Hydra override strings as one list of overrides, the strings last (they win).

    Raises:
        ConfigError: an override that is not ``key=value`` (or ``~key``), as the command line says it.
    """
    if isinstance(overrides, str):
        overrides = [overrides]
    out: list[str] = []
    for key, value in settings.items():
        if isinstance(value, Mapping) and "." not in key and value:
            out += [f"{key}.{sub}={hydra_text(v)}" for sub, v in _flat(value)]
        else:
            out.append(f"{key}={hydra_text(value)}")
    bad = [o for o in overrides if not isinstance(o, str) or not ("=" in o or o.startswith("~"))]
    if bad:
        raise ConfigError(f"overrides must look like key=value (or ~key to delete one), but got {bad}")
    return out + list(overrides)


def _flat(mapping: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``{"a": {"b": 1}}`` -> ``[("a.b", 1)]``; an empty mapping stays a value (``a={}``)."""
    out: list[tuple[str, Any]] = []
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out += _flat(value, name + ".")
        else:
            out.append((name, value))
    return out


# -- model ----------------------------------------------------------------------------------------------

def _model_entry(model: Any) -> tuple[str | None, dict[str, Any] | None]:
    """``(group option, None)`` for the name of a model config, or ``(None, model config)`` to write."""
    from physmend.modeling import Model

    if isinstance(model, str):
        if ":" not in model:
            return model, None
        where, func = model.rsplit(":", 1)
        if where.endswith(".py") or "/" in where or "\\" in where:
            where = str(Path(where).expanduser().resolve())
        return None, {"builder": f"{where}:{func}", "options": {}}
    if isinstance(model, Model) or callable(model):
        from physmend.api.models import register

        return None, {"builder": register(model), "options": {}}
    raise ConfigError("model must be a physmend Model, a builder function, 'path/to/file.py:function', "
                      f"'package.module:function' or the name of a model config, but got {type(model).__name__}")


# -- data -----------------------------------------------------------------------------------------------

def _data_entry(data: Any) -> tuple[str | None, dict[str, Any] | None, list[tuple[str, Any]]]:
    """``(group option, None, [])`` for the name of a data config; else ``(None, data config, tables)``
    where ``tables`` are ``(file name, DataFrame)`` to write beside it (checked, not yet written)."""
    if isinstance(data, (str, Path)):
        path = Path(data).expanduser()
        if isinstance(data, str) and not path.suffix and "/" not in data and not path.exists():
            return data, None, []
        if not path.is_file():
            raise DataError(f"data: the data config file {str(path)!r} does not exist (a data config is a YAML "
                            "file, a mapping, physmend.Dataset / a list of physmend.Experiment, or a config name)")
        return None, _read_yaml(path.resolve()), []
    if isinstance(data, Dataset):
        config, tables = _tables(data)
        return None, config, tables
    if isinstance(data, Mapping):
        if data and all(isinstance(v, Experiment) for v in data.values()):
            exps = [Experiment(e.frame, e.role, e.parameters, e.initial, str(k)) for k, e in data.items()]
            config, tables = _tables(Dataset(exps))
            return None, config, tables
        return None, dict(data), []
    if isinstance(data, Sequence) and data and all(isinstance(e, Experiment) for e in data):
        config, tables = _tables(Dataset(list(data)))
        return None, config, tables
    raise DataError("data must be a data config (a YAML file's path or a mapping), a config name, a physmend.Dataset "
                    f"or a list of physmend.Experiment tables, but got {type(data).__name__}")


def _read_yaml(path: Path) -> dict[str, Any]:
    """A data config file as a mapping, ``${project:}`` standing for the folder above its config
    directory (``my_project/`` for ``my_project/conf/data/plant.yaml``)."""
    from physmend.config import PROJECT

    from physmend.modeling.safe_yaml import load_bounded

    raw = load_bounded(path, DataError, where=f"data config {path}")
    if not isinstance(raw, Mapping):
        raise DataError(f"data config {path} must be a mapping of keys (name, root, experiments …), "
                        f"but holds {type(raw).__name__}")
    project = str(path.parent.parent)

    def swap(node: Any) -> Any:
        if isinstance(node, str):
            return node.replace(PROJECT, project)
        if isinstance(node, Mapping):
            return {k: swap(v) for k, v in node.items()}
        if isinstance(node, list):
            return [swap(v) for v in node]
        return node

    return swap(dict(raw))


def _tables(data: Dataset) -> tuple[dict[str, Any], list[tuple[str, Any]]]:
    """Check every table of ``data`` (before anything is written) and return the data config and files.

    Raises:
        DataError: a table that is not a DataFrame, lacks the time column or a role, or a role
            unknown, an id twice, no training experiment; the message names the experiment.
    """
    import pandas as pd

    if not data.experiments:
        raise DataError("data: no experiments given; pass at least one physmend.Experiment with role 'train'")
    time = str(data.time_column)
    seen: set[str] = set()
    rows: list[dict[str, Any]] = []
    tables: list[tuple[str, Any]] = []
    for i, e in enumerate(data.experiments):
        eid = str(e.id) if e.id is not None else str(i + 1)
        where = f"experiment {eid!r} (data[{i}])"
        if not isinstance(e.frame, pd.DataFrame):
            raise DataError(f"{where}: frame must be a pandas DataFrame, but got {type(e.frame).__name__}")
        if time not in e.frame.columns:
            cols = ", ".join(map(str, list(e.frame.columns)[:12]))
            raise DataError(f"{where}: the table has no time column {time!r} (its columns: {cols or 'none'}); expected a "
                            f"column {time!r} of sample times (or name yours with Dataset(time_column=...))")
        if e.role is None or str(e.role) == "":
            raise DataError(f"{where}: role is missing; expected one of {', '.join(ROLES)}")
        if e.role not in ROLES:
            raise DataError(f"{where}: role must be one of {', '.join(ROLES)}, but got {e.role!r}")
        if eid in seen:
            raise DataError(f"{where}: id {eid!r} is given twice; each experiment needs its own id")
        seen.add(eid)
        file = f"{i + 1:03d}_{_SAFE.sub('_', eid)[:60]}.csv"
        row: dict[str, Any] = {"id": eid, "file": file, "role": str(e.role)}
        if e.parameters:
            row["parameters"] = {str(k): _plain(v) for k, v in e.parameters.items()}
        if e.initial:
            row["initial"] = {str(k): _plain(v) for k, v in e.initial.items()}
        rows.append(row)
        tables.append((file, e.frame))
    if not any(r["role"] == "train" for r in rows):
        roles = sorted({r["role"] for r in rows})
        raise DataError(f"data: the role 'train' is missing: at least one experiment must have role 'train', "
                        f"but the roles given are {roles}")
    config: dict[str, Any] = {"name": str(data.name), "time_column": time, "experiments": rows}
    if data.time_unit is not None:
        config["time_unit"] = str(data.time_unit)
    if data.columns:
        config["columns"] = {str(k): str(v) for k, v in data.columns.items()}
    if data.validation_fraction is not None:
        config["validation_fraction"] = float(data.validation_fraction)
    return config, tables


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value.item() if hasattr(value, "item") else value


# -- everything -----------------------------------------------------------------------------------------

def prepare(model: Any = None, data: Any = None, *, settings: Mapping[str, Any] | None = None,
            overrides: Sequence[str] | str = (), config_dir: str | Path | None = None,
            base: Inputs | None = None) -> Inputs:
    """The overrides and config directory of one call; writes the workspace only after every check.

    ``base``: the inputs of an earlier result this call continues (its model, data and settings),
    which ``model``/``data``/settings given here replace.
    """
    extra = setting_overrides(settings or {}, overrides)
    if config_dir is not None and not Path(config_dir).expanduser().is_dir():
        where = str(Path(config_dir).expanduser().resolve())
        raise ConfigError(f"--config-dir must be an existing directory, but {where!r} is not")
    model_option, model_cfg = (None, None) if model is None else _model_entry(model)
    data_option, data_cfg, tables = (None, None, []) if data is None else _data_entry(data)
    choices = [f"model={model_option or OPTION}"] if model is not None else []
    choices += [f"data={data_option or OPTION}"] if data is not None else []
    start = base or Inputs()
    user_dir = str(Path(config_dir).expanduser().resolve()) if config_dir is not None else start.config_dir
    carried = start.workspace if config_dir is not None else None  # its model/data configs go on with us
    if model_cfg is None and data_cfg is None and carried is None:
        if config_dir is not None:
            return Inputs(start.with_settings([*choices, *extra]).overrides, user_dir, None)
        return start.with_settings([*choices, *extra])
    ws = Workspace()
    ws.parent = start.workspace  # its telemetry may be named by configs copied from it
    try:
        _write(ws, user_dir, model_cfg, data_cfg, tables)
        for group in ("model", "data"):
            staged = carried.conf / group / f"{OPTION}.yaml" if carried is not None else None
            if staged is not None and staged.is_file() and not (ws.conf / group / f"{OPTION}.yaml").exists():
                (ws.conf / group).mkdir(parents=True, exist_ok=True)
                shutil.copyfile(staged, ws.conf / group / f"{OPTION}.yaml")
    except BaseException:
        ws.remove()
        raise
    return Inputs(start.with_settings([*choices, *extra]).overrides, str(ws.conf), ws)


def _write(ws: Workspace, user_dir: str | None, model_cfg: dict[str, Any] | None,
           data_cfg: dict[str, Any] | None, tables: list[tuple[str, Any]]) -> None:
    """The workspace's config directory (a copy of the user's, ``${project:}`` of its model and data
    configs made absolute) with the call's model/data configs and telemetry files."""
    import yaml

    if user_dir is not None:
        from physmend.config import PROJECT

        shutil.copytree(user_dir, ws.conf, symlinks=False)
        project = str(Path(user_dir).parent)
        for group in ("model", "data"):
            for path in (ws.conf / group).glob("*.yaml"):
                text = path.read_text()
                if PROJECT in text:
                    path.write_text(text.replace(PROJECT, project))
    for group, cfg in (("model", model_cfg), ("data", data_cfg)):
        if cfg is None:
            continue
        (ws.conf / group).mkdir(parents=True, exist_ok=True)
        if group == "data" and tables:
            root = ws.path / "telemetry"
            root.mkdir()
            for name, frame in tables:
                frame.to_csv(root / name, index=False)
            cfg = {**cfg, "root": str(root)}
        (ws.conf / group / f"{OPTION}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
