"""The data config: where the telemetry lives and what each experiment is.

Schema (an OmegaConf ``DictConfig`` or a plain mapping)::

    name: my_plant
    root: ${project:}/telemetry    # or a path ('~' expands, relative = cwd) or pkg://<package>/<subdir>
    time_column: time              # seconds (numeric); default "time"
    time_unit: s                   # s (default) or the model's own time unit (tu …): shown as it is, never converted
    columns: {}                    # model name -> column name in the files; default {}
    validation_fraction: 0.2       # used when no experiment has role validation; default 0.2
    experiments:
      - id: "1"
        file: exp1.csv             # CSV or Parquet, relative to root (or absolute)
        role: train                # train | validation | test
        parameters: {zone1.length: 9.0}   # overrides of model parameter defaults (optional)
        initial: {}                # known initial state values (optional); a two-element list
                                   # [low, high] declares an unknown initial value, estimated
                                   # per experiment within these bounds (an unmeasured state)

Everything that can be checked without reading a file (keys, roles, ids, parameter and state
names, values) is checked here, before any telemetry is read.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from physmend.data.errors import DataError
from physmend.data.raw import _check_typos, _did_you_mean, _number, to_plain
from physmend.data.root import resolve_root

if TYPE_CHECKING:
    from physmend.modeling.simplify import SimplifiedModel

ROLES: tuple[str, ...] = ("train", "validation", "test")
"""The experiment roles, in the order they are reported."""

DEFAULT_TIME_COLUMN = "time"
DEFAULT_VALIDATION_FRACTION = 0.2

_TOP_KEYS = ("name", "root", "time_column", "time_unit", "columns", "validation_fraction", "experiments")
_EXP_KEYS = ("id", "file", "role", "parameters", "initial")


@dataclass(frozen=True)
class ExperimentSpec:
    """One entry of ``experiments:``, checked against the model.

    Attributes:
        id: experiment id (always a string).
        file: absolute path of the telemetry file (not yet checked for existence).
        role: ``"train"``, ``"validation"`` or ``"test"``.
        parameters: parameter name -> overriding value (model units).
        initial: state name -> initial value (model units): the known value, or the middle of
            the declared range where it is unknown.
        initial_ranges: state name -> ``(low, high)`` for initial values declared unknown
            (estimated per experiment within these bounds).
        index: position in the ``experiments`` list (for messages).
    """

    id: str
    file: Path
    role: str
    parameters: dict[str, float] = field(default_factory=dict)
    initial: dict[str, float] = field(default_factory=dict)
    index: int = 0
    initial_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def where(self) -> str:
        """How messages name this experiment: ``experiment '1' (file exp1.csv)``."""
        return f"experiment {self.id!r} (file {self.file.name})"


@dataclass(frozen=True)
class DataConfig:
    """A checked data config.

    Attributes:
        name: config name (for messages); ``"data"`` when not given.
        root: absolute folder the experiment files are relative to.
        time_column: name of the time column (seconds) in every file.
        columns: model output/input name -> column name in the files (only non-identity entries
            need to be given).
        validation_fraction: fraction of each training record carved off as validation when no
            experiment has role validation; checked to lie in (0, 1) only when it is used.
        experiments: the experiments in config order.
    """

    name: str
    root: Path
    time_column: str
    columns: dict[str, str]
    validation_fraction: Any
    experiments: tuple[ExperimentSpec, ...]

    def column_for(self, variable: str) -> str:
        """The file column holding model output/input ``variable``."""
        return self.columns.get(variable, variable)

    @property
    def has_validation(self) -> bool:
        """Whether any experiment has role ``validation`` (then nothing is carved)."""
        return any(e.role == "validation" for e in self.experiments)


# -- helpers ---------------------------------------------------------------------------------------

def time_unit_of(data_cfg: Any) -> str:
    """``time_unit`` of a data config: ``s`` (default: times are seconds) or the name of the
    model's own time unit (``tu``, ``dimensionless`` …: shown as it is, never converted).

    Raises:
        DataError: not a short word (letters, digits, ``_ . / -``, at most 24 characters).
    """
    value = data_cfg.get("time_unit", "s")
    value = "s" if value is None else value
    if not isinstance(value, str) or not re.fullmatch(r"[A-Za-z0-9_./-]{1,24}", value):
        name = data_cfg.get("name") or "data"
        raise DataError(f"data config {name!r}: `time_unit` must be a short unit name (letters, digits, _ . / -; "
                        f"at most 24 characters), e.g. s or tu, but got {value!r}")
    return value


# -- parsing ---------------------------------------------------------------------------------------


def parse_data_config(data_cfg: Any, model: SimplifiedModel) -> DataConfig:
    """Check ``data_cfg`` against the schema and ``model``; resolve the root and file paths.

    Raises:
        DataError: one per problem, naming the key (and the experiment's id and file) and what was
            expected.
    """
    cfg = to_plain(data_cfg)
    if not isinstance(cfg, Mapping):
        raise DataError(f"data config must be a mapping, but got {type(cfg).__name__}")
    name = str(cfg.get("name") or "data")
    where = f"data config {name!r}"
    _check_typos(cfg, _TOP_KEYS, where)
    for key in ("root", "experiments"):
        if key not in cfg or cfg[key] is None:
            raise DataError(f"{where}: missing required key {key!r}")
    root = resolve_root(cfg["root"], config_name=name)

    time_unit_of(cfg)
    time_column = cfg.get("time_column", DEFAULT_TIME_COLUMN)
    if not isinstance(time_column, str) or not time_column:
        raise DataError(f"{where}: `time_column` must be a column name, but got {time_column!r}")

    columns = _parse_columns(cfg.get("columns"), model, where)

    fraction = cfg.get("validation_fraction", DEFAULT_VALIDATION_FRACTION)

    raw = cfg["experiments"]
    if not isinstance(raw, list):
        raise DataError(f"{where}: `experiments` must be a list, but got {type(raw).__name__}")
    if not raw:
        raise DataError(f"{where}: `experiments` is empty; list at least one train experiment")
    specs: list[ExperimentSpec] = []
    seen: dict[str, int] = {}
    for i, entry in enumerate(raw):
        spec = _parse_experiment(entry, i, root, model, where)
        if spec.id in seen:
            first = specs[seen[spec.id]]
            raise DataError(
                f"{where}: experiment ids must be unique, but id {spec.id!r} is used by "
                f"experiments[{first.index}] (file {first.file.name}) and experiments[{i}] "
                f"(file {spec.file.name})"
            )
        seen[spec.id] = len(specs)
        specs.append(spec)

    if not any(s.role == "train" for s in specs):
        roles = {s.id: s.role for s in specs}
        raise DataError(
            f"{where}: at least one experiment must have role 'train', but the roles are {roles}"
        )
    if not any(s.role == "validation" for s in specs):
        if isinstance(fraction, bool):
            fraction = None
        try:
            fval = float(fraction)
        except (TypeError, ValueError):
            fval = math.nan
        if not 0.0 < fval < 1.0:
            raise DataError(
                f"{where}: no experiment has role 'validation', so `validation_fraction` (the last "
                f"part of each training record held out for validation) must lie in (0, 1), "
                f"but got {fraction!r}"
            )
        fraction = fval
    return DataConfig(
        name=name,
        root=root,
        time_column=time_column,
        columns=columns,
        validation_fraction=fraction,
        experiments=tuple(specs),
    )


def _parse_columns(raw: Any, model: SimplifiedModel, where: str) -> dict[str, str]:
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise DataError(
            f"{where}: `columns` must map model output/input names to file column names, "
            f"but got {raw!r}"
        )
    channels = list(model.output_names) + [n for n in model.input_names if n not in model.outputs]
    other = {n: "state" for n in model.state_names}
    other.update({n: "parameter" for n in model.parameter_names})
    other.update({n: "algebraic variable" for n in getattr(model, "observed", {})})
    out: dict[str, str] = {}
    for key, col in raw.items():
        key = str(key)
        if key not in channels:
            if key in other:
                article = "an" if other[key][0] in "aeiou" else "a"
                why = (
                    f"is {article} {other[key]} of model {model.name!r}, not a measured output "
                    "or input"
                )
            else:
                why = f"is not a variable of model {model.name!r}" + _did_you_mean(key, channels)
            raise DataError(
                f"{where}: `columns` maps {key!r}, which {why}; `columns` keys must be model "
                f"outputs or inputs: {channels}"
            )
        if not isinstance(col, str) or not col:
            raise DataError(
                f"{where}: `columns.{key}` must be the name of a file column, but got {col!r}"
            )
        out[key] = col
    return out


def _parse_experiment(
    entry: Any, index: int, root: Path, model: SimplifiedModel, where: str
) -> ExperimentSpec:
    if not isinstance(entry, Mapping):
        raise DataError(
            f"{where}: experiments[{index}] must be a mapping with keys {list(_EXP_KEYS)}, "
            f"but got {entry!r}"
        )
    label = f"{where}: experiments[{index}]"
    known = [f"id {str(entry['id'])!r}"] if entry.get("id") is not None else []
    known += [f"file {entry['file']}"] if entry.get("file") is not None else []
    if known:
        label += f" ({', '.join(known)})"
    for key in ("id", "file", "role"):
        if entry.get(key) is None or (isinstance(entry.get(key), str) and not entry[key].strip()):
            raise DataError(f"{label}: missing required key {key!r}")
    _check_typos(entry, _EXP_KEYS, label)
    exp_id = str(entry["id"])
    file = entry["file"]
    if not isinstance(file, (str, Path)):
        raise DataError(f"{label}: `file` must be a file name or path, but got {file!r}")
    path = Path(file).expanduser()
    path = path if path.is_absolute() else root / path
    label = f"{where}: experiment {exp_id!r} (file {path.name})"

    role = entry["role"]
    if role not in ROLES:
        raise DataError(f"{label}: `role` must be one of {list(ROLES)}, but got {role!r}")

    params_raw = entry.get("parameters") or {}
    if not isinstance(params_raw, Mapping):
        raise DataError(
            f"{label}: `parameters` must map parameter names to values, but got {params_raw!r}"
        )
    known_params = model.parameter_names
    parameters: dict[str, float] = {}
    for key, value in params_raw.items():
        key = str(key)
        if key not in known_params:
            raise DataError(
                f"{label}: `parameters` sets {key!r}, which is not a parameter of model "
                f"{model.name!r}{_did_you_mean(key, known_params)}"
            )
        parameters[key] = _number(value, f"{label}: parameter {key!r}")

    initial, ranges = _parse_initial(entry.get("initial") or {}, model, label)
    return ExperimentSpec(
        id=exp_id,
        file=path,
        role=role,
        parameters=parameters,
        initial=initial,
        index=index,
        initial_ranges=ranges,
    )


def _parse_initial(
    init_raw: Any, model: SimplifiedModel, label: str
) -> tuple[dict[str, float], dict[str, tuple[float, float]]]:
    """``initial:`` of one experiment: known values, and ``[low, high]`` ranges of unknown ones."""
    if not isinstance(init_raw, Mapping):
        raise DataError(
            f"{label}: `initial` must map state names to initial values or [low, high] ranges, but got {init_raw!r}"
        )
    states = model.state_names
    initial: dict[str, float] = {}
    ranges: dict[str, tuple[float, float]] = {}
    for key, value in init_raw.items():
        key = str(key)
        if key not in states:
            raise DataError(
                f"{label}: `initial` sets {key!r}, which is not a state of model {model.name!r}"
                f"{_did_you_mean(key, states)} (states: {states})"
            )
        if isinstance(value, Sequence) and not isinstance(value, str):
            bounds = list(value)
            what = f"{label}: initial range of {key!r}"
            if len(bounds) != 2:
                raise DataError(f"{what} must be [low, high] (two numbers), but got {bounds!r}")
            low, high = (_number(b, what) for b in bounds)
            if not low < high:
                raise DataError(f"{what} must satisfy low < high, but got [{low:g}, {high:g}] (an empty range)")
            ranges[key] = (low, high)
            initial[key] = 0.5 * (low + high)
        else:
            initial[key] = _number(value, f"{label}: initial value of {key!r}")
    return initial, ranges
