"""Good telemetry loads: CSV and Parquet, irregular sampling, gaps, mapping, parameters, split."""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from physmend.data import (
    Channel,
    DataError,
    Experiment,
    experiments_by_role,
    load_experiments,
    summarize_experiments,
)

NAN = np.nan


def test_csv_and_parquet_load_alike(cfg, model):
    exps = load_experiments(cfg, model)
    assert [e.id for e in exps] == ["1", "2", "3"]
    assert [e.role for e in exps] == ["train", "train", "test"]
    e1, e2, e3 = exps
    assert all(isinstance(e, Experiment) for e in exps)
    assert e1.file.name == "exp1.csv" and e2.file.name == "exp2.parquet"
    assert e1.t0 == 100.0 and e2.t0 == 1100.0 and e3.t0 == 50.0
    for other in (e2, e3):
        np.testing.assert_allclose(other.obs_time, e1.obs_time, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(np.isnan(other.obs), np.isnan(e1.obs))
        np.testing.assert_allclose(other.obs, e1.obs, equal_nan=True)
        np.testing.assert_allclose(other.inputs["amb.T"].time, e1.inputs["amb.T"].time, atol=1e-12)
    assert e1.obs.dtype == np.float64 and e1.obs_time.dtype == np.float64
    assert e1.t_end == pytest.approx(10.0)


def test_irregular_sampling_gaps_and_rates_are_preserved(cfg, model):
    e = load_experiments(cfg, model)[0]
    # row 0 (t=99) has no output: not an observation row; t0 is the first row with an output
    np.testing.assert_allclose(e.obs_time, [0.0, 0.5, 1.7, 3.0, 4.2, 6.0, 8.1, 10.0])
    assert e.obs.shape == (8, 2)
    a, b = e.obs[:, 0], e.obs[:, 1]  # model.output_names order: a.T, b.T
    assert np.isnan(a[3]) and a[4] == 20.9  # gap in a.T kept as NaN, not zero
    np.testing.assert_array_equal(np.isnan(b), [False, True, True, False, True, True, True, False])
    np.testing.assert_allclose(b[~np.isnan(b)], [19.0, 19.2, 19.5])
    ch = e.inputs["amb.T"]
    assert isinstance(ch, Channel) and list(e.inputs) == ["amb.T"]
    # the input keeps its own samples: the NaN at t=101.7 is left out, t=99 (before t0) kept
    np.testing.assert_allclose(ch.time, [-1.0, 0.0, 0.5, 3.0, 4.2, 6.0, 8.1, 10.0])
    np.testing.assert_allclose(ch.values, [25.0, 25.0, 25.1, 25.3, 25.2, 25.0, 24.9, 24.8])
    assert np.all(np.isfinite(ch.values)) and np.all(np.diff(ch.time) > 0)


def test_channels_at_different_rates(tmp_path, model, writer):
    # the input at 1 Hz, a.T every 2 s, b.T every 5 s, all in one table
    t = np.arange(0.0, 21.0)
    df = pd.DataFrame({"time": t, "amb.T": 20 + 0.1 * t})
    df["a.T"] = np.where(t % 2 == 0, 1.0 + t, NAN)
    df["b.T"] = np.where(t % 5 == 0, 2.0 + t, NAN)
    writer(df, tmp_path / "rates.parquet")
    cfg = {"root": str(tmp_path), "experiments": [{"id": 1, "file": "rates.parquet", "role": "train"}]}
    (e,) = load_experiments(cfg, model)
    assert e.id == "1"
    # observation rows: where a.T or b.T is measured (b.T alone at 5 and 15)
    expected = sorted(set(range(0, 21, 2)) | set(range(0, 21, 5)))
    np.testing.assert_allclose(e.obs_time, expected)
    np.testing.assert_array_equal(e.obs_time[~np.isnan(e.obs[:, 0])], np.arange(0.0, 21.0, 2.0))
    np.testing.assert_array_equal(e.obs_time[~np.isnan(e.obs[:, 1])], [0.0, 5.0, 10.0, 15.0, 20.0])
    assert len(e.inputs["amb.T"]) == 21


def test_column_mapping_and_time_column(tmp_path, model, writer, good_df):
    df = good_df.rename(columns={"time": "t_s", "a.T": "T_a", "amb.T": "ambient"})
    writer(df, tmp_path / "mapped.csv")
    cfg = {
        "root": str(tmp_path),
        "time_column": "t_s",
        "columns": {"a.T": "T_a", "amb.T": "ambient"},
        "experiments": [{"id": "m", "file": "mapped.csv", "role": "train"}],
    }
    (e,) = load_experiments(cfg, model)
    assert e.t0 == 100.0
    assert np.isnan(e.obs[3, 0]) and e.obs[4, 0] == 20.9
    assert list(e.inputs) == ["amb.T"] and e.inputs["amb.T"].values[0] == 25.0


def test_parameters_override_defaults_and_initial(cfg, model):
    e1, e2, _ = load_experiments(cfg, model)
    assert model.parameter_names == ["a.C", "k"]
    np.testing.assert_array_equal(e1.parameters, [12.0, 0.5])
    np.testing.assert_array_equal(e2.parameters, [10.0, 0.5])
    assert e1.parameters.dtype == np.float64
    assert e1.initial == {} and e2.initial == {"b.T": 19.0}


def test_validation_carving_sets_split_time(cfg, model):
    exps = load_experiments(cfg, model)
    for e in experiments_by_role(exps, "train"):
        expected = e.obs_time[0] + (1 - 0.2) * (e.t_end - e.obs_time[0])
        assert e.split_time == pytest.approx(expected) == pytest.approx(8.0)
    assert experiments_by_role(exps, "test")[0].split_time is None
    assert experiments_by_role(exps, "validation") == []
    cfg["validation_fraction"] = 0.5
    assert load_experiments(cfg, model)[0].split_time == pytest.approx(5.0)
    assert "validation carved from t >= 5 s" in summarize_experiments(load_experiments(cfg, model))


def test_default_validation_fraction(cfg, model):
    del cfg["validation_fraction"]
    assert load_experiments(cfg, model)[0].split_time == pytest.approx(8.0)


def test_explicit_validation_role_leaves_split_none(cfg, model):
    cfg["experiments"][1]["role"] = "validation"
    cfg["validation_fraction"] = 7  # not used, so not checked
    exps = load_experiments(cfg, model)
    assert all(e.split_time is None for e in exps)
    assert [e.id for e in experiments_by_role(exps, "validation")] == ["2"]
    assert [e.id for e in experiments_by_role(exps, "train")] == ["1"]


def test_omegaconf_config(cfg, model):
    dc = OmegaConf.create(cfg)
    exps = load_experiments(dc, model)
    assert [e.id for e in exps] == ["1", "2", "3"]


def test_relative_root_and_home(cfg, model, data_dir, monkeypatch):
    monkeypatch.chdir(data_dir.parent)
    cfg["root"] = data_dir.name
    assert load_experiments(cfg, model)[0].file == data_dir / "exp1.csv"
    monkeypatch.setenv("HOME", str(data_dir.parent))
    cfg["root"] = "~/" + data_dir.name
    assert load_experiments(cfg, model)[0].file == data_dir / "exp1.csv"
    # absolute file path ignores root
    cfg["root"] = "/nonexistent"
    cfg["experiments"] = [{"id": "a", "file": str(data_dir / "exp1.csv"), "role": "train"}]
    assert load_experiments(cfg, model)[0].t0 == 100.0


def test_pkg_root(tmp_path, model, writer, good_df, monkeypatch):
    pkg = tmp_path / "site" / "rig_pkg_for_tests"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    writer(good_df, pkg / "telemetry" / "exp1.csv")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    cfg = {
        "root": "pkg://rig_pkg_for_tests/telemetry",
        "experiments": [{"id": "1", "file": "exp1.csv", "role": "train"}],
    }
    (e,) = load_experiments(cfg, model)
    assert e.file == (pkg / "telemetry" / "exp1.csv").resolve()
    sys.modules.pop("rig_pkg_for_tests", None)


def test_input_exactly_covering_span(tmp_path, model, writer):
    df = pd.DataFrame(
        {"time": [0.0, 1.0, 2.0], "a.T": [1.0, 2.0, 3.0], "b.T": [1.0, NAN, 3.0], "amb.T": [5.0, NAN, 6.0]}
    )
    writer(df, tmp_path / "e.csv")
    cfg = {"root": str(tmp_path), "experiments": [{"id": "1", "file": "e.csv", "role": "train"}]}
    (e,) = load_experiments(cfg, model)
    assert e.inputs["amb.T"].span == (0.0, 2.0)


def test_experiments_by_role_rejects_unknown_role(cfg, model):
    exps = load_experiments(cfg, model)
    with pytest.raises(DataError, match="'training'"):
        experiments_by_role(exps, "training")


def test_text_typed_numbers_and_na_text_load(tmp_path, model, writer, good_df):
    # a Parquet file whose output column is stored as text: numbers parse, "nan"/"" stay NaN
    good_df["a.T"] = ["nan", "20.0", "20.1", "20.3", "", "20.9", "21.4", "21.8", "22.0"]
    writer(good_df, tmp_path / "text.parquet")
    cfg = {"root": str(tmp_path), "experiments": [{"id": "1", "file": "text.parquet", "role": "train"}]}
    (e,) = load_experiments(cfg, model)
    assert np.isnan(e.obs[3, 0]) and e.obs[1, 0] == 20.1


def test_loading_leaves_files_unchanged(cfg, model, data_dir):
    before = {p: p.read_bytes() for p in data_dir.iterdir()}
    load_experiments(cfg, model)
    assert {p: p.read_bytes() for p in data_dir.iterdir()} == before
