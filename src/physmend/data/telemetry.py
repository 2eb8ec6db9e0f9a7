"""Reading telemetry files (CSV or Parquet) and checking their columns.

A telemetry file has a time column (seconds) and one column per measured output and per exogenous
input. NaN (an empty CSV cell) means "not measured here", never zero. Files are only read, never
written.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from physmend.data.errors import DataError

CSV_SUFFIXES: tuple[str, ...] = (".csv", ".csv.gz", ".csv.bz2", ".csv.xz", ".csv.zst", ".csv.zip")
PARQUET_SUFFIXES: tuple[str, ...] = (".parquet", ".pq")
_NA_TEXT = frozenset({"", "nan", "na", "n/a", "null", "none", "<na>"})
"""Texts read as "not measured" in a text column (pandas already does this for CSV cells)."""
QUOTE = 60
"""Characters of a file's text an error quotes at most (a cell or header may be megabytes long)."""


def shown(value: object, limit: int = QUOTE) -> str:
    """``repr(value)`` cut to about ``limit`` characters, saying how long it was."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text)} characters)"


def shown_columns(columns: list[str], limit: int = 8) -> str:
    """The first ``limit`` column names (each cut), and how many there are in all."""
    head = ", ".join(shown(c, 30) for c in columns[:limit])
    return f"[{head}]" if len(columns) <= limit else f"[{head}, …] ({len(columns)} columns)"


@dataclass
class Channel:
    """One sampled signal.

    Attributes:
        time: ``(n,)`` float64, seconds relative to the experiment start ``t0``; finite samples
            only, strictly increasing (may start before 0 for inputs recorded before ``t0``).
        values: ``(n,)`` float64, finite, in the model's unit of the signal.
    """

    time: np.ndarray
    values: np.ndarray

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def span(self) -> tuple[float, float]:
        """``(first, last)`` sample time, seconds relative to ``t0``."""
        return float(self.time[0]), float(self.time[-1])


def file_format(path: Path, *, where: str = "") -> str:
    """``"csv"`` or ``"parquet"`` from the file name, else a DataError listing the supported ones.

    ``where`` (optional) names the experiment for the message.
    """
    name = path.name.lower()
    if name.endswith(CSV_SUFFIXES):
        return "csv"
    if name.endswith(PARQUET_SUFFIXES):
        return "parquet"
    prefix = f"{where}: " if where else ""
    suffix = "".join(path.suffixes) or "(no suffix)"
    raise DataError(
        f"{prefix}telemetry file {str(path)!r} has unsupported format {suffix!r}; "
        f"telemetry must be CSV ({', '.join(CSV_SUFFIXES)}) or Parquet "
        f"({', '.join(PARQUET_SUFFIXES)})"
    )


def read_table(path: Path, *, where: str) -> pd.DataFrame:
    """Read the telemetry file ``path`` (CSV or Parquet) into a DataFrame, rows in file order.

    ``where`` names the experiment for messages. Raises DataError when the file is missing, has
    an unsupported format, cannot be parsed, or has no data rows.
    """
    if not path.exists():
        raise DataError(f"{where}: telemetry file {str(path)!r} not found")
    if not path.is_file():
        raise DataError(f"{where}: telemetry file {str(path)!r} is not a file")
    fmt = file_format(path, where=where)
    try:
        if fmt == "csv":
            df = pd.read_csv(path)
        else:
            df = pd.read_parquet(path)
    except Exception as exc:  # parser, decoding, Arrow and OS errors alike
        kind = "CSV" if fmt == "csv" else "Parquet"
        raise DataError(
            f"{where}: telemetry file {str(path)!r} cannot be read as {kind}: "
            f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
        ) from exc
    df.columns = [str(c) for c in df.columns]
    if len(df) == 0:
        raise DataError(
            f"{where}: telemetry file {str(path)!r} has no data rows (columns: {shown_columns(list(df.columns))})"
        )
    return df.reset_index(drop=True)


def row_label(i: int, fmt: str) -> str:
    """How messages name data row ``i`` (0-based): CSV rows also get their line number."""
    return f"row {i} (line {i + 2} of the CSV)" if fmt == "csv" else f"row {i}"


def numeric_column(df: pd.DataFrame, column: str, *, where: str, fmt: str, what: str) -> np.ndarray:
    """Column ``column`` as an ``(n,)`` float64 array; NaN stays NaN (not measured).

    Raises DataError if the column holds text, dates or other non-numbers, or infinite values.
    ``what`` says what the column is for (``"model output 'a.T'"``).
    """
    series = df[column]
    if isinstance(series, pd.DataFrame):
        raise DataError(f"{where}: column {column!r} ({what}) appears more than once")
    if pd.api.types.is_bool_dtype(series.dtype):
        values = series.to_numpy(dtype=np.float64, na_value=np.nan)
    elif pd.api.types.is_numeric_dtype(series.dtype) and not pd.api.types.is_complex_dtype(
        series.dtype
    ):
        values = series.to_numpy(dtype=np.float64, na_value=np.nan)
    elif pd.api.types.is_object_dtype(series.dtype) or pd.api.types.is_string_dtype(series.dtype):
        coerced = pd.to_numeric(series, errors="coerce")
        blank = series.map(lambda x: isinstance(x, str) and x.strip().lower() in _NA_TEXT)
        bad = np.flatnonzero(
            coerced.isna().to_numpy() & series.notna().to_numpy() & ~blank.to_numpy(dtype=bool)
        )
        if bad.size:
            i = int(bad[0])
            raise DataError(
                f"{where}: column {column!r} ({what}) must be numeric, but "
                f"{row_label(i, fmt)} holds {shown(series.iloc[i])}"
            )
        values = coerced.to_numpy(dtype=np.float64, na_value=np.nan)
    else:
        raise DataError(
            f"{where}: column {column!r} ({what}) must be numeric, but has type {series.dtype}"
        )
    inf = np.flatnonzero(np.isinf(values))
    if inf.size:
        i = int(inf[0])
        raise DataError(
            f"{where}: column {column!r} ({what}) must hold finite numbers or NaN (not measured), "
            f"but {row_label(i, fmt)} holds {float(values[i])}"
        )
    return values


def time_column(df: pd.DataFrame, column: str, *, where: str, fmt: str) -> np.ndarray:
    """The time column as ``(n,)`` float64 seconds: numeric, finite, strictly increasing."""
    if column not in df.columns:
        raise DataError(
            f"{where}: time column {column!r} is missing; columns present: {shown_columns(list(df.columns))} "
            "(set `time_column:` in the data config if time is named differently)"
        )
    t = numeric_column(df, column, where=where, fmt=fmt, what="time, seconds")
    nan = np.flatnonzero(np.isnan(t))
    if nan.size:
        raise DataError(
            f"{where}: time column {column!r} must be finite in every row, but "
            f"{row_label(int(nan[0]), fmt)} is empty/NaN"
        )
    if t.size > 1:
        step = np.diff(t)
        bad = np.flatnonzero(step <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            if t[i] == t[i - 1]:
                found = f"{row_label(i, fmt)} repeats time {float(t[i])!r} (duplicate time)"
            else:
                found = f"{row_label(i, fmt)} has time {float(t[i])!r} after {float(t[i - 1])!r}"
            raise DataError(
                f"{where}: time column {column!r} must be strictly increasing, but {found}"
            )
    return t
