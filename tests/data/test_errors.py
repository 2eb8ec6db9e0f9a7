"""Every bad input raises one DataError naming the file and the column/key; files are untouched."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from physmend.data import DataError, load_experiments

NAN = np.nan


def snapshot(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# Each case: setup(cfg, root, writer, df) mutates the config and/or writes a bad file; the
# message must contain every listed fragment. "{root}" is replaced by the data folder.
Setup = Callable[[dict[str, Any], Path, Callable, pd.DataFrame], None]


def _exp(cfg: dict[str, Any], i: int = 0) -> dict[str, Any]:
    return cfg["experiments"][i]


def _bad_file(name: str, mutate: Callable[[pd.DataFrame], pd.DataFrame]) -> Setup:
    def setup(cfg, root, writer, df):
        writer(mutate(df.copy()), root / name)
        _exp(cfg)["file"] = name

    return setup


def _set(df: pd.DataFrame, col: str, values: list[Any]) -> pd.DataFrame:
    df[col] = values
    return df


def _swap_rows(df: pd.DataFrame) -> pd.DataFrame:
    t = df["time"].to_list()
    t[5], t[6] = t[6], t[5]
    df["time"] = t
    return df


def _dup_time(df: pd.DataFrame) -> pd.DataFrame:
    t = df["time"].to_list()
    t[4] = t[3]
    df["time"] = t
    return df


def _nan_time(df: pd.DataFrame) -> pd.DataFrame:
    df["time"] = df["time"].astype(float)
    df.loc[2, "time"] = NAN
    return df


def _text_in(df: pd.DataFrame) -> pd.DataFrame:
    df["a.T"] = df["a.T"].astype(object)
    df.loc[2, "a.T"] = "abc"
    return df


def _text_column(df: pd.DataFrame) -> pd.DataFrame:
    # a string-typed column (as Parquet stores it): numbers and "nan" as text, one bad cell
    df["a.T"] = ["nan", "20.0", "abc", "20.3", "", "20.9", "21.4", "21.8", "22.0"]
    return df


def _inf_in(df: pd.DataFrame) -> pd.DataFrame:
    df.loc[2, "b.T"] = np.inf
    return df


def _short_input(df: pd.DataFrame) -> pd.DataFrame:
    df["amb.T"] = [NAN, NAN, 25.1, NAN, 25.3, 25.2, 25.0, 24.9, NAN]
    return df


def _one_obs_row(df: pd.DataFrame) -> pd.DataFrame:
    df["a.T"] = [NAN, 20.0] + [NAN] * 7
    df["b.T"] = [NAN, 19.0] + [NAN] * 7
    return df


def _write_raw(name: str, content: bytes) -> Setup:
    def setup(cfg, root, writer, df):
        (root / name).write_bytes(content)
        _exp(cfg)["file"] = name

    return setup


def _cfg(fn: Callable[[dict[str, Any]], None]) -> Setup:
    def setup(cfg, root, writer, df):
        fn(cfg)

    return setup


def _upd(d: dict[str, Any], **kw: Any) -> None:
    d.update(kw)


CASES: list[Any] = [
    pytest.param(
        _cfg(lambda c: c.update(time_unit="${oc.env:HOME} hours")),
        ["`time_unit` must be a short unit name", "'${oc.env:HOME} hours'"],
        id="bad-time-unit",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), file="nope.csv")),
        ["{root}/nope.csv", "experiment '1'", "not found"],
        id="file-not-found",
    ),
    pytest.param(
        _write_raw("exp1.txt", b"time,a.T\n1,2\n"),
        ["exp1.txt", "unsupported format", "'.txt'", "experiment '1'"],
        id="unsupported-format",
    ),
    pytest.param(
        _write_raw("broken.parquet", b"this is not parquet at all"),
        ["broken.parquet", "cannot be read as Parquet", "experiment '1'"],
        id="unreadable-parquet",
    ),
    pytest.param(
        _write_raw("empty.csv", b""),
        ["empty.csv", "cannot be read as CSV"],
        id="empty-csv",
    ),
    pytest.param(
        _write_raw("header.csv", b"time,a.T,b.T,amb.T\n"),
        ["header.csv", "no data rows"],
        id="header-only",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, time_column="t")),
        ["exp1.csv", "time column 't' is missing", "'a.T'"],
        id="missing-time-column",
    ),
    pytest.param(
        _bad_file("nob.csv", lambda d: d.drop(columns=["b.T"])),
        ["nob.csv", "model output 'b.T'", "columns:", "present columns", "'note'"],
        id="missing-output-column",
    ),
    pytest.param(
        _bad_file("nou.parquet", lambda d: d.drop(columns=["amb.T"])),
        ["nou.parquet", "model input 'amb.T'", "columns:", "Expected columns"],
        id="missing-input-column",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, columns={"a.T": "Ta"})),
        ["exp1.csv", "model output 'a.T'", "'Ta'", "columns:"],
        id="mapped-column-missing",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, columns={"zz.T": "x"})),
        ["data config 'rig'", "columns", "'zz.T'", "not a variable"],
        id="mapping-unknown-variable",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, columns={"a.q": "x"})),
        ["data config 'rig'", "'a.q'", "is an algebraic variable", "columns"],
        id="mapping-algebraic-variable",
    ),
    pytest.param(
        _bad_file("text.csv", _text_in),
        ["text.csv", "'a.T'", "must be numeric", "row 2", "'abc'"],
        id="non-numeric-column",
    ),
    pytest.param(
        _bad_file("text.parquet", _text_column),
        ["text.parquet", "'a.T'", "must be numeric", "row 2", "'abc'"],
        id="non-numeric-column-parquet",
    ),
    pytest.param(
        _bad_file("inf.csv", _inf_in),
        ["inf.csv", "'b.T'", "finite", "row 2"],
        id="infinite-value",
    ),
    pytest.param(
        _bad_file("order.csv", _swap_rows),
        ["order.csv", "'time'", "strictly increasing", "row 6", "104.2 after 106.0"],
        id="time-not-increasing",
    ),
    pytest.param(
        _bad_file("dup.parquet", _dup_time),
        ["dup.parquet", "'time'", "strictly increasing", "row 4", "duplicate", "101.7"],
        id="duplicate-time",
    ),
    pytest.param(
        _bad_file("nantime.csv", _nan_time),
        ["nantime.csv", "'time'", "finite", "row 2"],
        id="nan-time",
    ),
    pytest.param(
        _bad_file("textime.csv", lambda d: _set(d, "time", ["a"] * 9)),
        ["textime.csv", "'time'", "must be numeric"],
        id="non-numeric-time",
    ),
    pytest.param(
        _bad_file("allnan.csv", lambda d: _set(d, "b.T", [NAN] * 9)),
        ["allnan.csv", "'b.T'", "all 9 rows are empty"],
        id="output-all-nan",
    ),
    pytest.param(
        _bad_file("allnanu.parquet", lambda d: _set(d, "amb.T", [NAN] * 9)),
        ["allnanu.parquet", "'amb.T'", "all 9 rows are empty"],
        id="input-all-nan",
    ),
    pytest.param(
        _bad_file("short.csv", _short_input),
        ["short.csv", "input 'amb.T'", "[100.0, 110.0]", "[100.5, 108.1]"],
        id="input-not-covering",
    ),
    pytest.param(
        _bad_file("one.csv", _one_obs_row),
        ["one.csv", "at least 2 rows", "has 1"],
        id="single-observation",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), parameters={"a.c": 3.0})),
        ["exp1.csv", "'a.c'", "not a parameter", "close matches: ['a.C']"],
        id="unknown-parameter",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), parameters={"k": float("nan")})),
        ["exp1.csv", "parameter 'k'", "finite number", "nan"],
        id="nan-parameter",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), parameters={"k": "fast"})),
        ["exp1.csv", "parameter 'k'", "finite number", "'fast'"],
        id="text-parameter",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), initial={"a.q": 1.0})),
        ["exp1.csv", "'a.q'", "not a state", "'a.T'"],
        id="initial-not-a-state",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), initial={"a.T": float("inf")})),
        ["exp1.csv", "'a.T'", "finite number"],
        id="initial-not-finite",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c, 2), role="holdout")),
        ["exp3.csv", "role", "'holdout'", "'validation'"],
        id="unknown-role",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c, 2), id="1")),
        ["exp3.csv", "exp1.csv", "unique", "'1'", "experiments[0]", "experiments[2]"],
        id="duplicate-id",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, root="pkg://no_such_pkg_xyz/telemetry")),
        ["no_such_pkg_xyz", "not importable", "root"],
        id="pkg-not-importable",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, experiments=[])),
        ["data config 'rig'", "`experiments` is empty"],
        id="empty-experiments",
    ),
    pytest.param(
        _cfg(lambda c: c.pop("experiments")),
        ["data config 'rig'", "missing required key 'experiments'"],
        id="missing-experiments",
    ),
    pytest.param(
        _cfg(lambda c: c.pop("root")),
        ["data config 'rig'", "missing required key 'root'"],
        id="missing-root",
    ),
    pytest.param(
        _cfg(lambda c: _exp(c).pop("id")),
        ["experiments[0]", "exp1.csv", "missing required key 'id'"],
        id="missing-id",
    ),
    pytest.param(
        _cfg(lambda c: _exp(c, 1).pop("file")),
        ["experiments[1]", "id '2'", "missing required key 'file'"],
        id="missing-file",
    ),
    pytest.param(
        _cfg(lambda c: _exp(c, 2).pop("role")),
        ["experiments[2]", "exp3.csv", "missing required key 'role'"],
        id="missing-role",
    ),
    pytest.param(
        _cfg(lambda c: _upd(_exp(c), paramters={"k": 1.0})),
        ["exp1.csv", "'paramters'", "did you mean 'parameters'"],
        id="misspelt-key",
    ),
    pytest.param(
        _cfg(lambda c: [_upd(e, role="test") for e in c["experiments"]]),
        ["data config 'rig'", "role 'train'"],
        id="no-train-experiment",
    ),
    pytest.param(
        _cfg(lambda c: _upd(c, validation_fraction=1.5)),
        ["data config 'rig'", "validation_fraction", "(0, 1)", "1.5"],
        id="validation-fraction-out-of-range",
    ),
]


@pytest.mark.parametrize(("setup", "fragments"), CASES)
def test_bad_input_raises_one_clear_error(setup, fragments, cfg, model, data_dir, writer, good_df):
    setup(cfg, data_dir, writer, good_df)
    before = snapshot(data_dir.parent)
    with pytest.raises(DataError) as info:
        load_experiments(cfg, model)
    message = str(info.value)
    for fragment in fragments:
        assert fragment.replace("{root}", str(data_dir)) in message, message
    assert snapshot(data_dir.parent) == before  # nothing written, nothing changed


def test_data_error_is_a_value_error():
    assert issubclass(DataError, ValueError)
