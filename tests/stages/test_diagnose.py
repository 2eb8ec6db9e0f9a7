"""physmend diagnose on a user's own (non-thermal) model, through the CLI, with a real MLflow sqlite store."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from physmend.cli import main


def _tree_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def test_diagnose_runs_unchanged_on_a_user_model(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    import mlflow
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(user_project)
    before = _tree_hashes(user_project / "recordings")
    rc = main(["diagnose", "--config-dir", str(user_project / "my_conf"), "model=oscillator", "data=oscillator"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "physmend diagnose — model `oscillator`" in out
    assert "The model misses the recordings" in out
    assert _tree_hashes(user_project / "recordings") == before  # the user's data is untouched

    db = user_project / "mlflow.db"
    assert db.is_file()
    client = MlflowClient(tracking_uri=f"sqlite:///{db}")
    exp = client.get_experiment_by_name("physmend")
    runs = client.search_runs([exp.experiment_id])
    assert len(runs) == 1
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.tags["physmend.stage"] == "diagnose"
    assert run.data.tags["physmend.data"] == "oscillator"
    assert run.info.run_id in out
    # the missing drag shows: error well above the ~3 mm sensor noise, on train and test runs
    for run_name in ("run1", "run2", "run3"):
        assert run.data.metrics[f"rmse.{run_name}.cart.x"] > 5 * run.data.metrics[f"noise.{run_name}.cart.x"]
        assert 0.001 < run.data.metrics[f"noise.{run_name}.cart.x"] < 0.01
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"config.yaml", "summary.md", "diagnosis.json", "plots"} <= artifacts
    plots = {a.path for a in client.list_artifacts(run.info.run_id, "plots")}
    assert plots == {"plots/fit_run1.png", "plots/fit_run2.png", "plots/fit_run3.png"}
    # the artifacts sit beside the database, not in the working directory's default places
    assert (user_project / "mlartifacts").is_dir()
    # the drift of the position error follows the velocity the drag depends on
    text = Path(client.download_artifacts(run.info.run_id, "summary.md", str(user_project))).read_text()
    line = next(l for l in text.splitlines() if l.startswith("- **cart.x**"))
    assert "cart.v" in line or "damper.F" in line
    mlflow.set_tracking_uri(None)


def test_bad_data_is_one_clear_error_and_writes_nothing(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    csv = user_project / "recordings" / "run2.csv"
    text = csv.read_text().replace("motor.F", "motor_force")
    csv.write_text(text)
    before = _tree_hashes(user_project)
    rc = main(["diagnose", "--config-dir", str(user_project / "my_conf"), "model=oscillator", "data=oscillator"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "run2.csv" in err and "motor.F" in err
    assert err.count("\n") <= 3  # one message, no traceback
    assert _tree_hashes(user_project) == before  # no mlflow.db, no artifacts, data unchanged
    assert not (user_project / "mlflow.db").exists()


def test_bad_override_and_unknown_model_file_are_clear_errors(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    rc = main(["diagnose", "--config-dir", str(user_project / "my_conf"), "data=no_such_data"])
    err = capsys.readouterr().err
    assert rc == 2 and "data=no_such_data names no option of config group 'data'" in err and "oscillator" in err
    assert len(err.strip().splitlines()) == 1
    rc = main(["diagnose", "model.builder=/nowhere/model.py:build"])
    err = capsys.readouterr().err
    assert rc == 2 and "/nowhere/model.py" in err and "does not exist" in err
    assert not (user_project / "mlflow.db").exists()
