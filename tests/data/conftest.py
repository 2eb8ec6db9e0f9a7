"""Shared fixtures: a small real model and telemetry files written with pandas/pyarrow."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from physmend.modeling import Model, SimplifiedModel


def build_model() -> SimplifiedModel:
    """2 states, 1 input, 2 outputs, 2 parameters, one algebraic equation."""
    m = Model("rig")
    t1 = m.state("a.T", start=20.0, unit="degC")
    t2 = m.state("b.T", start=20.0, unit="degC")
    q = m.variable("a.q", unit="W")
    c = m.parameter("a.C", 10.0, unit="J/K")
    k = m.parameter("k", 0.5, unit="W/K")
    u = m.input("amb.T", unit="degC")
    m.equation(q, k * (t1 - t2), owner="a")
    m.equation(c * m.der(t1), -q + (u - t1), owner="a")
    m.equation(m.der(t2), q, owner="b")
    m.output("a.T", t1, unit="degC")
    m.output("b.T", t2, unit="degC")
    return m.simplify()


NAN = np.nan

# Irregular times; row 0 has only the input (before the experiment start); b.T at a lower rate;
# a.T has a gap (NaN) at row 4; amb.T has a gap at row 3; an extra column is ignored.
GOOD = pd.DataFrame(
    {
        "time": [99.0, 100.0, 100.5, 101.7, 103.0, 104.2, 106.0, 108.1, 110.0],
        "a.T": [NAN, 20.0, 20.1, 20.3, NAN, 20.9, 21.4, 21.8, 22.0],
        "b.T": [NAN, 19.0, NAN, NAN, 19.2, NAN, NAN, NAN, 19.5],
        "amb.T": [25.0, 25.0, 25.1, NAN, 25.3, 25.2, 25.0, 24.9, 24.8],
        "note": [1, 2, 3, 4, 5, 6, 7, 8, 9],
    }
)


def write(df: pd.DataFrame, path: Path) -> Path:
    """Write ``df`` as CSV or Parquet depending on the suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix in (".parquet", ".pq"):
        df.to_parquet(path, index=False)
    else:
        df.to_csv(path, index=False)
    return path


def shifted(df: pd.DataFrame, dt: float) -> pd.DataFrame:
    out = df.copy()
    out["time"] = out["time"] + dt
    return out


@pytest.fixture
def model() -> SimplifiedModel:
    return build_model()


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    """A root folder with exp1.csv, exp2.parquet and exp3.csv (all good)."""
    root = tmp_path / "telemetry"
    write(GOOD, root / "exp1.csv")
    write(shifted(GOOD, 1000.0), root / "exp2.parquet")
    write(shifted(GOOD, -50.0), root / "exp3.csv")
    return root


@pytest.fixture
def cfg(data_dir: Path) -> dict[str, Any]:
    """A plain-dict data config over ``data_dir`` (train, train, test)."""
    return {
        "name": "rig",
        "root": str(data_dir),
        "time_column": "time",
        "columns": {},
        "validation_fraction": 0.2,
        "experiments": [
            {"id": "1", "file": "exp1.csv", "role": "train", "parameters": {"a.C": 12.0}},
            {"id": "2", "file": "exp2.parquet", "role": "train", "initial": {"b.T": 19.0}},
            {"id": "3", "file": "exp3.csv", "role": "test"},
        ],
    }


@pytest.fixture
def good_df() -> pd.DataFrame:
    """A copy of the good telemetry table (see ``GOOD``)."""
    return GOOD.copy()


@pytest.fixture
def writer():
    """``writer(df, path)`` writes CSV or Parquet depending on the suffix."""
    return write
