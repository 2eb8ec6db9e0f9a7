"""Experiments: telemetry records matched to a model, with their role and configuration."""

from __future__ import annotations

import difflib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from physmend.data.config import ROLES, DataConfig, ExperimentSpec, parse_data_config
from physmend.data.errors import DataError
from physmend.data.sanity import check_magnitude
from physmend.data.telemetry import (
    Channel,
    file_format,
    numeric_column,
    read_table,
    row_label,
    shown_columns,
    time_column,
)

if TYPE_CHECKING:
    import pandas as pd

    from physmend.modeling.simplify import SimplifiedModel

log = logging.getLogger(__name__)


@dataclass
class Experiment:
    """One telemetry record, checked against the model.

    Attributes:
        id: experiment id from the data config.
        role: ``"train"``, ``"validation"`` or ``"test"``.
        file: absolute path of the telemetry file.
        t0: absolute time (s, the file's time column) of the experiment start: the first row with
            at least one measured output.
        obs_time: ``(n_t,)`` float64 seconds relative to ``t0``, strictly increasing, starting at
            0; the rows where at least one output is measured.
        obs: ``(n_t, n_outputs)`` float64, columns in ``model.output_names`` order; NaN = not
            measured in that row.
        inputs: model input name -> :class:`Channel` (finite samples only, times relative to
            ``t0``), in ``model.input_names`` order; each covers ``[0, t_end]``.
        parameters: ``(n_params,)`` float64, model defaults overridden by the config, in
            ``model.parameter_names`` order.
        initial: state name -> initial value (at ``t0``): known, or the middle of its range.
        initial_ranges: state name -> ``(low, high)`` of initial values declared unknown
            (estimated per experiment within these bounds).
        split_time: relative time (s) from which observations count as validation, when a
            validation slice is carved from this training record; None otherwise.
    """

    id: str
    role: str
    file: Path
    t0: float
    obs_time: np.ndarray
    obs: np.ndarray
    inputs: dict[str, Channel]
    parameters: np.ndarray
    initial: dict[str, float] = field(default_factory=dict)
    split_time: float | None = None
    initial_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def t_end(self) -> float:
        """Last observation time, seconds relative to ``t0``."""
        return float(self.obs_time[-1])

    def __repr__(self) -> str:
        split = "" if self.split_time is None else f", split_time={self.split_time:g}"
        return (
            f"Experiment(id={self.id!r}, role={self.role!r}, file={self.file.name!r}, "
            f"t0={self.t0!r}, n_t={len(self.obs_time)}, t_end={self.t_end!r}{split})"
        )


def experiments_by_role(exps: list[Experiment], role: str) -> list[Experiment]:
    """The experiments of ``exps`` whose role is ``role`` (config order kept).

    Carved validation slices are not separate experiments: a training experiment with a
    ``split_time`` is returned for ``"train"`` only.
    """
    if role not in ROLES:
        raise DataError(f"role must be one of {list(ROLES)}, but got {role!r}")
    return [e for e in exps if e.role == role]


def load_experiments(data_cfg: Any, model: SimplifiedModel, *, dtype: Any = np.float64) -> list[Experiment]:
    """Read and check every experiment of the data config ``data_cfg`` against ``model``.

    The config is checked completely before any file is read; files are only read, never
    written. Either every experiment loads or one :class:`DataError` is raised (no partial
    result).

    Args:
        data_cfg: the data config (``DictConfig`` or mapping; see :mod:`physmend.data.config`).
        model: the simplified model whose outputs, inputs, parameters and states the telemetry
            and config refer to.
        dtype: the arithmetic the model is simulated in (``simulate.dtype``): every value must be
            small enough for it (:func:`physmend.data.sanity.check_magnitude`).

    Returns:
        The experiments in config order. When no experiment has role ``validation``, every
        training experiment gets ``split_time = obs_time[0] + (1 - validation_fraction) *
        (t_end - obs_time[0])``.
    """
    cfg = parse_data_config(data_cfg, model)
    if not model.output_names:
        raise DataError(
            f"data config {cfg.name!r}: model {model.name!r} declares no measured outputs, "
            "so telemetry cannot be compared with it"
        )
    exps = [_load_one(spec, cfg, model, dtype) for spec in cfg.experiments]
    if not cfg.has_validation:
        frac = float(cfg.validation_fraction)
        for e in exps:
            if e.role == "train":
                start = float(e.obs_time[0])
                e.split_time = start + (1.0 - frac) * (e.t_end - start)
    return exps


def summarize_experiments(exps: list[Experiment]) -> str:
    """A few lines naming each experiment, its role, span and (carved) validation slice."""
    lines = []
    for e in exps:
        line = f"{e.id}: {e.role}, {e.file.name}, {len(e.obs_time)} observation rows over {e.t_end:g} s"
        if e.split_time is not None:
            line += f"; validation carved from t >= {e.split_time:g} s"
        lines.append(line)
    return "\n".join(lines)


# -- one experiment --------------------------------------------------------------------------------


def _display(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:
        return str(path)


def _load_one(spec: ExperimentSpec, cfg: DataConfig, model: SimplifiedModel, dtype: Any = np.float64) -> Experiment:
    where = f"experiment {spec.id!r} (file {_display(spec.file, cfg.root)})"
    df = read_table(spec.file, where=f"experiment {spec.id!r}")
    fmt = file_format(spec.file)
    t_abs = time_column(df, cfg.time_column, where=where, fmt=fmt)

    outputs, inputs = list(model.output_names), list(model.input_names)
    _check_columns(df, cfg, outputs, inputs, where)
    used = {cfg.time_column} | {cfg.column_for(n) for n in outputs + inputs}
    extra = [c for c in df.columns if c not in used]
    if extra:
        log.debug("%s: ignoring columns %s", where, extra)

    obs_all = np.empty((len(df), len(outputs)), dtype=np.float64)
    for j, name in enumerate(outputs):
        obs_all[:, j] = _channel_values(df, cfg, name, "model output", where, fmt, dtype)
    measured = ~np.isnan(obs_all).all(axis=1)
    rows = np.flatnonzero(measured)
    if rows.size < 2:
        raise DataError(
            f"{where}: needs at least 2 rows with a measured output ({outputs}), "
            f"but has {rows.size}"
        )
    t0 = float(t_abs[rows[0]])
    obs_time = t_abs[rows] - t0
    obs = obs_all[rows]
    t_end = float(obs_time[-1])

    channels: dict[str, Channel] = {}
    tol = 1e-9 * max(1.0, abs(t0) + t_end)
    for name in inputs:
        v = _channel_values(df, cfg, name, "model input", where, fmt, dtype)
        ok = ~np.isnan(v)
        ch = Channel(time=t_abs[ok] - t0, values=v[ok])
        first, last = ch.span
        if first > tol or last < t_end - tol:
            col = cfg.column_for(name)
            via = f" (column {col!r})" if col != name else ""
            covered = [float(t_abs[ok][0]), float(t_abs[ok][-1])]
            needed = [t0, float(t_abs[rows[-1]])]
            raise DataError(
                f"{where}: input {name!r}{via} must cover the simulated span {needed} s "
                f"(file time, first to last row with a measured output), but its samples cover "
                f"{covered} s"
            )
        channels[name] = ch

    params = np.array([float(p.value) for p in model.parameters], dtype=np.float64)
    index = {n: i for i, n in enumerate(model.parameter_names)}
    for key, value in spec.parameters.items():
        check_magnitude(np.array([float(value)]), where=f"data config {cfg.name!r}, experiment {spec.id!r}",
                        label=f"parameter {key!r}", row=lambda i: "parameters", dtype=dtype)
        params[index[key]] = value
    return Experiment(
        id=spec.id,
        role=spec.role,
        file=spec.file,
        t0=t0,
        obs_time=obs_time,
        obs=obs,
        inputs=channels,
        parameters=params,
        initial=dict(spec.initial),
        split_time=None,
        initial_ranges=dict(spec.initial_ranges),
    )


def _check_columns(
    df: pd.DataFrame, cfg: DataConfig, outputs: list[str], inputs: list[str], where: str
) -> None:
    present = list(df.columns)
    expected = [cfg.time_column] + [cfg.column_for(n) for n in outputs + inputs]
    unused = [c for c in present if c not in expected]
    missing: list[str] = []
    for kind, names in (("model output", outputs), ("model input", inputs)):
        for name in names:
            col = cfg.column_for(name)
            if col in df.columns:
                continue
            text = f"{kind} {name!r}"
            if col != name:
                text += f" (mapped to column {col!r} by `columns:`)"
            close = difflib.get_close_matches(col, unused, n=2, cutoff=0.6)
            if close:
                text += f" (close matches: {close})"
            missing.append(text)
    if missing:
        raise DataError(
            f"{where}: no column for {'; '.join(missing)}. Expected columns {expected}, "
            f"present columns {shown_columns(present)}. If the file names a channel differently, map it in "
            "the data config under `columns:` (model name -> column name)"
        )


def _channel_values(
    df: pd.DataFrame, cfg: DataConfig, name: str, kind: str, where: str, fmt: str, dtype: Any = np.float64
) -> np.ndarray:
    col = cfg.column_for(name)
    what = f"{kind} {name!r}"
    v = numeric_column(df, col, where=where, fmt=fmt, what=what)
    if np.isnan(v).all():
        raise DataError(
            f"{where}: column {col!r} ({what}) has no measured value: all {v.size} rows are "
            "empty/NaN; every output and input needs at least one sample"
        )
    label = f"column {col!r} ({kind})" if col == name else f"column {col!r} ({what})"
    check_magnitude(v, where=where, label=label, row=lambda i: row_label(i, fmt), dtype=dtype)
    return v


__all__ = [
    "Experiment",
    "experiments_by_role",
    "load_experiments",
    "summarize_experiments",
]
