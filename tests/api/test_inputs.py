"""The Python API's inputs: bad settings and bad tables are one PhysmendError naming the key or column,
with the command line's own message, and nothing written; a model object and DataFrames give the same
diagnose run as the command line on the files (real store, no mocks)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
import pytest

import physmend
from physmend.cli import main

ROOT = Path(__file__).resolve().parents[2]
CSTR = ROOT / "examples" / "cstr"


def _tables() -> list[physmend.Experiment]:
    """The bundled reactor's two records as DataFrames, with the roles and initial values of its data config."""
    return [physmend.Experiment(pd.read_csv(CSTR / "telemetry" / "r1.csv"), role="train", id="r1",
                                initial={"reactor.A": 0.2, "reactor.B": 2.5}),
            physmend.Experiment(pd.read_csv(CSTR / "telemetry" / "r2.csv"), role="test", id="r2",
                                initial={"reactor.A": 1.6, "reactor.B": 0.4})]


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _cli_error(capsys: pytest.CaptureFixture[str], *args: str) -> str:
    rc = main(["diagnose", *args])
    err = capsys.readouterr().err
    assert rc == 2, err
    return err.strip().removeprefix("physmend diagnose: error: ")


@pytest.mark.parametrize("call, cli, named", [
    (dict(sweep={"n_trialz": 4}), ["sweep.n_trialz=4"], "sweep.n_trialz"),
    (dict(sweep={"n_trials": "many"}), ["sweep.n_trials=many"], "sweep.n_trials"),
    ({"train.epochs": 2.5}, ["train.epochs=2.5"], "train.epochs"),
    (dict(overrides=["simulate.rtol=-1"]), ["simulate.rtol=-1"], "simulate.rtol"),
])
def test_a_bad_setting_is_the_command_lines_error_and_writes_nothing(
        call: dict, cli: list[str], named: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    expected = _cli_error(capsys, "model=cstr", "data=cstr", *cli)
    with pytest.raises(physmend.PhysmendError) as caught:
        physmend.diagnose("cstr", "cstr", **call)
    assert type(caught.value).__name__ == "ConfigError"
    assert str(caught.value) == expected and named in expected, (str(caught.value), expected)
    assert _tree(tmp_path) == []  # no store, no file: nothing written


def test_a_table_without_the_time_column_names_it_and_writes_nothing(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    tables = _tables()
    bad = physmend.Experiment(tables[1].frame.rename(columns={"time": "t_min"}), role="test", id="r2")
    with pytest.raises(physmend.PhysmendError) as caught:
        physmend.diagnose(str(CSTR / "model.py") + ":build", [tables[0], bad])
    message = str(caught.value)
    assert type(caught.value).__name__ == "DataError"
    assert "experiment 'r2'" in message and "no time column 'time'" in message and "t_min" in message, message
    assert _tree(tmp_path) == []


@pytest.mark.parametrize("roles, named", [(("train", None), "role is missing"),
                                          (("test", "test"), "the role 'train' is missing"),
                                          (("train", "holdout"), "but got 'holdout'")])
def test_a_missing_or_unknown_role_names_it_and_writes_nothing(roles: tuple, named: str, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    tables = [physmend.Experiment(t.frame, role=r, id=t.id, initial=t.initial) for t, r in zip(_tables(), roles)]
    before = set(Path(tempfile.gettempdir()).glob("physmend-api-*"))
    with pytest.raises(physmend.PhysmendError) as caught:
        physmend.diagnose("cstr", tables)
    assert named in str(caught.value), str(caught.value)
    assert _tree(tmp_path) == []
    assert set(Path(tempfile.gettempdir()).glob("physmend-api-*")) == before  # no workspace left


def test_settings_become_the_command_lines_overrides() -> None:
    from physmend.api.inputs import setting_overrides

    assert setting_overrides({"sweep": {"n_trials": 4, "space": "small"}, "train.lr": 0.01, "seed": 3,
                              "discover": {"budget": None}, "ude": {"inputs": {"states": ["a", "b"]}}},
                             ["symbolic.rule=knee"]) == [
        "sweep.n_trials=4", "sweep.space=small", "train.lr=0.01", "seed=3", "discover.budget=null",
        "ude.inputs.states=[a,b]", "symbolic.rule=knee"]
    with pytest.raises(physmend.PhysmendError, match="overrides must look like key=value"):
        setting_overrides({}, ["sweep.n_trials"])


def test_import_is_cheap_and_sweep_is_both_function_and_package() -> None:
    code = ("import sys, physmend; assert 'torch' not in sys.modules and 'mlflow' not in sys.modules; "
            "import physmend.sweep.loop; assert callable(physmend.sweep) and callable(physmend.symbolic); "
            "from physmend.sweep import hydra_value; print(physmend.sweep.loop.__name__)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "physmend.sweep.loop", done.stderr


def test_a_model_object_and_tables_make_the_command_lines_diagnose_run(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], reset_mlflow: None) -> None:
    monkeypatch.chdir(tmp_path)
    spec = importlib.util.spec_from_file_location("cstr_model_for_api_test", CSTR / "model.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    mine = physmend.diagnose(module.build(), physmend.Dataset(_tables(), name="cstr", time_unit="min"),
                             diagnose={"plots": False})
    assert main(["diagnose", "model=cstr", "data=cstr", "diagnose.plots=false"]) == 0
    cli_id = capsys.readouterr().out.split("diagnose run: ")[1].split()[0]
    assert mine.run_id != cli_id
    assert main(["runs", "--json"]) == 0  # `physmend runs` lists the run made from Python
    listed = {r["run_id"] for r in json.loads(capsys.readouterr().out)["stage_runs"]}
    assert {mine.run_id, cli_id} <= listed
    from physmend.api.artifacts import RunFiles

    cli = RunFiles(mine.files.store, cli_id).metrics()
    assert {k: pytest.approx(v, rel=1e-9) for k, v in mine.metrics.items()} == cli
    assert list(mine.fits["experiment"]) == ["r1", "r1", "r2", "r2"] and mine.fits["rmse"].gt(0).all()
    assert "worst misfit" in repr(mine) and "<table" in mine._repr_html_()
    assert "diagnose run: " + mine.run_id in mine.printed


@pytest.mark.slow
def test_tables_go_through_a_sweep_and_a_result_hands_on_its_selected_trial(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, reset_mlflow: None) -> None:
    """Each trial's configuration is composed from the call's own config folder (the tables written
    there), as the command line composes it; ``mask(sweep_result)`` starts from its selected trial."""
    monkeypatch.chdir(tmp_path)
    cheap = {"train": {"epochs": 20, "eval_every": 10}, "ude": {"depth": 1}, "diagnose": {"plots": False}}
    diagnosis = physmend.diagnose(str(CSTR / "model.py") + ":build", physmend.Dataset(_tables(), time_unit="min"),
                                  **cheap)
    swept = physmend.sweep(source=diagnosis, sweep={"n_trials": 1, "space": "small"})
    assert len(swept.trials) == 1 and swept.trials["state"].tolist() == ["COMPLETE"]
    assert swept.selected_run_id == swept.best_run_id == swept.trials["run_id"][0]
    masked = physmend.mask(swept, mask={"retrain": False})
    assert masked.files.tags()["physmend.source_run_id"] == swept.selected_run_id
    assert set(masked.kept) <= {"reactor.A", "reactor.B"} and len(masked.ranking) == 2
    workspace = Path(diagnosis.call.config_dir).parent
    assert (workspace / "telemetry").is_dir() and swept.call.workspace is diagnosis.call.workspace
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mlartifacts", "mlflow.db", "optuna.db"]


def test_a_later_call_with_its_own_config_folder_keeps_the_earlier_model_and_tables(tmp_path: Path) -> None:
    from physmend.api.inputs import prepare
    from physmend.config import compose

    mine = tmp_path / "conf" / "train"
    mine.mkdir(parents=True)
    (mine / "fast.yaml").write_text("defaults:\n  - default\n  - _self_\nepochs: 7\n")
    first = prepare(str(CSTR / "model.py") + ":build", _tables(), settings={"seed": 2})
    later = prepare(config_dir=tmp_path / "conf", overrides=["train=fast"], base=first)
    cfg = compose(list(later.overrides), user_config_dir=later.config_dir)
    assert cfg.train.epochs == 7 and cfg.seed == 2 and cfg.model.builder == f"{CSTR / 'model.py'}:build"
    assert [e["id"] for e in cfg.data.experiments] == ["r1", "r2"] and Path(cfg.data.root).is_dir()
    assert later.workspace.parent is first.workspace  # the tables stay while the later call's results live


def test_a_builder_in_a_file_is_named_by_its_file_and_others_are_registered(monkeypatch: pytest.MonkeyPatch) -> None:
    from physmend.api.models import register
    from physmend.modeling.loader import load_model

    spec = importlib.util.spec_from_file_location("cstr_model_named_by_file", CSTR / "model.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)
    spec.loader.exec_module(module)
    assert register(module.build) == f"{(CSTR / 'model.py').resolve()}:build"  # later commands can import it
    made = module.build()
    ref = register(made)  # an object: registered, a fresh copy per build, later edits of it change nothing
    assert ref.startswith("physmend.api.models:") and register(made) == ref
    first, second = load_model(ref), load_model(ref)
    assert first is not made and first is not second and first.name == made.name == "cstr"
    inline = register(lambda: module.build())  # a function defined in a notebook: registered too
    assert inline.startswith("physmend.api.models:") and load_model(inline).name == "cstr"
