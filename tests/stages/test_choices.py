"""Held-out data in no choice, and the same seed gives the same answer: ``physmend discover`` on a
user's project and on a copy whose *test* recording differs make the same choices — the same
selected trial, kept equations, formula and constants — while the held-out report differs.
And the user's settings win under discover: ``sweep.*`` given on the command line apply, and a
key the search space would search is left out of the search, said in one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
import yaml

from physmend.cli import main

TINY = ["model=oscillator", "data=oscillator", "train.epochs=40", "train.eval_every=20", "simulate.rtol=1e-6",
        "simulate.atol=1e-7", "ude.depth=1", "sweep.n_trials=1", "sweep.group=1", "mask.max_k=2", "train.lr=0.02",
        "symbolic.refit_epochs=10", "propose.plots=false", "sweep.figures=false"]


def _discover(project: Path, capsys) -> dict[str, object]:  # noqa: ANN001
    from mlflow.tracking import MlflowClient

    rc = main(["discover", "--config-dir", str(project / "my_conf"), *TINY])
    out = capsys.readouterr()
    assert rc == 0, out.err
    ids = dict(part.strip().split(" ", 1) for part in
               next(l for l in out.out.splitlines() if l.startswith("run IDs: "))[len("run IDs: "):].split(","))
    client = MlflowClient(tracking_uri=f"sqlite:///{project / 'mlflow.db'}")
    corrections = yaml.safe_load(Path(client.download_artifacts(ids["symbolic"], "corrections.yaml", str(project))).read_text())
    proposal = json.loads(Path(client.download_artifacts(ids["propose"], "proposal.json", str(project))).read_text())
    sweep = client.get_run(ids["sweep"]).data.tags
    said = [l for l in out.out.splitlines() if "given on the command line" in l]
    assert said == ["sweep: train.lr, ude.depth given on the command line: sweeps/default.yaml does not search them "
                    "in this sweep"], said
    trials = client.search_runs([client.get_run(ids["sweep"]).info.experiment_id],
                                f"tags.mlflow.parentRunId = '{ids['sweep']}'")
    assert len(trials) == 1  # sweep.n_trials=1 wins over discover.n_trials
    trial_cfg = yaml.safe_load(Path(client.download_artifacts(trials[0].info.run_id, "config.yaml", str(project))).read_text())
    assert trial_cfg["train"]["lr"] == 0.02
    return {
        "kept": client.get_run(ids["mask"]).data.tags["physmend.kept"],
        "mask_val": client.get_run(ids["mask"]).data.metrics["val.rmse"],
        "corrections": corrections["corrections"],
        "test_after": [r["after"] for r in proposal["rows"] if r["role"] == "test"],
        "best_trial": client.get_run(sweep["physmend.best_run_id"]).data.tags["physmend.trial_number"],
    }


@pytest.mark.slow
def test_changing_the_test_data_changes_no_choice(user_project: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys) -> None:  # noqa: ANN001
    other = tmp_path / "other"
    shutil.copytree(user_project, other)
    text = (other / "my_conf" / "data" / "oscillator.yaml").read_text().replace(str(user_project), str(other))
    (other / "my_conf" / "data" / "oscillator.yaml").write_text(text)
    (other / "my_conf" / "model" / "oscillator.yaml").write_text(
        (other / "my_conf" / "model" / "oscillator.yaml").read_text().replace(str(user_project), str(other)))
    test_file = other / "recordings" / "run3.csv"  # the test experiment: a different recording altogether
    frame = pd.read_csv(test_file)
    frame["position"] = frame["position"] * 0.5 + 0.1
    frame.to_csv(test_file, index=False)

    monkeypatch.chdir(user_project)
    first = _discover(user_project, capsys)
    monkeypatch.chdir(other)
    second = _discover(other, capsys)

    assert second["kept"] == first["kept"]
    assert second["best_trial"] == first["best_trial"]
    assert second["mask_val"] == pytest.approx(first["mask_val"], rel=1e-6)
    a, b = first["corrections"], second["corrections"]
    assert [(c["state"], c["term"]) for c in a] == [(c["state"], c["term"]) for c in b]
    for ca, cb in zip(a, b):
        assert cb["constants"].keys() == ca["constants"].keys()
        for k in ca["constants"]:
            assert cb["constants"][k] == pytest.approx(ca["constants"][k], rel=1e-6, abs=1e-9)
    assert second["test_after"] != first["test_after"]  # the report did see the other test data
