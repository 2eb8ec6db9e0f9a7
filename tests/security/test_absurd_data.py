"""Data no simulation can use is named before any work starts, in one line with its real cause and
what to do, in the data's own time unit: a value beyond float64 arithmetic (1e300 in a measured
column), a record sampled so finely that the solver could not pass its rows (2,000,000 rows where 40
describe the dynamics), a cell of a megabyte of text (quoted in a few dozen characters). Real files,
copied from ``examples/predator_prey`` (time in ``tu``); ``physmend diagnose`` on each."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "predator_prey"

Cli = Callable[..., tuple[int, str]]


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the predator-prey example (the original is never touched)."""
    folder = tmp_path / "predator_prey"
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.chdir(tmp_path)
    return folder


def _diagnose(project: Path, run_cli: Cli, *words: str) -> str:
    start = time.perf_counter()
    rc, err = run_cli("diagnose", "--config-dir", str(project / "conf"), "model=predator_prey",
                      "data=predator_prey", "diagnose.plots=false")
    assert time.perf_counter() - start < 10
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line and len(line) <= 300, line
    for word in words:
        assert word in line, (word, line)
    assert not (project.parent / "mlflow.db").exists()  # refused before a store or run was made
    return line


def test_a_value_beyond_float64_arithmetic_is_named(project: Path, run_cli: Cli) -> None:
    path = project / "telemetry" / "h2.csv"
    df = pd.read_csv(path)
    df.loc[5, "prey.x"] = 1e300
    df.to_csv(path, index=False)
    _diagnose(project, run_cli, "experiment 'h2' (file h2.csv)", "column 'prey.x'", "1e+300", "line 7",
              "float64", "larger unit")


def test_an_input_or_parameter_beyond_float64_arithmetic_is_named(project: Path, run_cli: Cli) -> None:
    path = project / "telemetry" / "h3.csv"
    df = pd.read_csv(path)
    df.loc[7, "stocking.u"] = -3e200
    df.to_csv(path, index=False)
    _diagnose(project, run_cli, "experiment 'h3'", "column 'stocking.u' (model input)", "-3e+200")
    shutil.copy(EXAMPLE / "telemetry" / "h3.csv", path)
    data = project / "conf" / "data" / "predator_prey.yaml"
    data.write_text(data.read_text().replace("parameters: {prey.K: 7.0}", "parameters: {prey.K: 7.0e299}"))
    _diagnose(project, run_cli, "experiment 'h2'", "parameter 'prey.K'", "7e+299")


def test_a_record_sampled_far_finer_than_the_model_needs_is_named_with_what_to_do(project: Path, run_cli: Cli) -> None:
    """2,000,001 rows over the same 30 tu (Parquet: written in a second; a CSV reads the same way)."""
    original = pd.read_csv(project / "telemetry" / "h1.csv")
    t = np.linspace(float(original.time.iloc[0]), float(original.time.iloc[-1]), 2_000_001)
    fine = pd.DataFrame({c: np.interp(t, original.time, original[c]) for c in original.columns})
    fine.to_parquet(project / "telemetry" / "h1.parquet", index=False)
    data = project / "conf" / "data" / "predator_prey.yaml"
    data.write_text(data.read_text().replace("file: h1.csv", "file: h1.parquet"))
    line = _diagnose(project, run_cli, "experiment 'h1' (file h1.parquet)", "2000001 rows", "1.5e-05 tu",
                     "fastest time constant", "100000", "simulate.options.max_steps", "resample", "1 row in 41")
    assert " s " not in line and " s)" not in line  # the model's own time unit throughout


def test_every_example_still_loads() -> None:
    """The rules are general: none of the shipped examples is refused (all of them, data only)."""
    from physmend.config import compose
    from physmend.problem import load_problem

    for folder in sorted((EXAMPLE.parent).iterdir()):
        if (folder / "conf" / "data").is_dir():
            cfg = compose([f"model={folder.name}", f"data={folder.name}"], user_config_dir=folder / "conf")
            assert load_problem(cfg).experiments, folder.name


def test_a_megabyte_cell_is_quoted_in_a_few_dozen_characters(project: Path, run_cli: Cli) -> None:
    path = project / "telemetry" / "h2.csv"
    df = pd.read_csv(path).astype({"prey.x": object})
    df.loc[3, "prey.x"] = "A" * 1_000_000
    df.to_csv(path, index=False)
    _diagnose(project, run_cli, "column 'prey.x'", "must be numeric", "1000002 characters")


def test_an_overlong_message_is_cut_in_the_middle() -> None:
    from physmend.cli import MAX_MESSAGE, bounded

    text = "physmend x: error: start " + "y" * 50_000 + " end"
    cut = bounded(text)
    assert len(cut) <= MAX_MESSAGE + 60 and cut.startswith("physmend x: error: start") and cut.endswith(" end")
    assert bounded("short") == "short"
