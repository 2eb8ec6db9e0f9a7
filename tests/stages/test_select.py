"""physmend runs / physmend select: listing, overriding the automatic choice, clear errors that change nothing."""

from __future__ import annotations

import getpass
import json
import textwrap
from pathlib import Path
from typing import Any

import pytest
from omegaconf import OmegaConf

from physmend.cli import main

TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=4", "train.eval_every=2", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.progress=false",
]
SPACE = """\
description: two good trials, one that diverges, one that is pruned
params:
  ude.output_scale: {choice: [0.1, 1.0e+300]}
  train.lr: {choice: [0.01, 0.005, 1.0e-7]}
  ude.width: {choice: [4]}
first_trials:
  - {ude.output_scale: 0.1, train.lr: 0.01}
  - {ude.output_scale: 0.1, train.lr: 0.005}
  - {ude.output_scale: 1.0e+300, train.lr: 0.01}
  - {ude.output_scale: 0.1, train.lr: 1.0e-7}
"""


@pytest.fixture(autouse=True)
def _reset_mlflow() -> Any:
    yield
    import mlflow

    mlflow.set_tracking_uri(None)


def snapshot(client: Any) -> dict[str, Any]:
    """Everything a selection could change, for every run of every experiment."""
    out = {}
    for exp in client.search_experiments():
        for run in client.search_runs([exp.experiment_id]):
            out[run.info.run_id] = (run.info.status, dict(run.data.tags), dict(run.data.params), dict(run.data.metrics))
    return out


def test_runs_and_select(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    from physmend.tracking import TrackingError, current_selection, load_trial, open_store

    monkeypatch.chdir(user_project)
    conf = ["--config-dir", str(user_project / "my_conf")]
    space = user_project / "space.yaml"
    space.write_text(textwrap.dedent(SPACE))
    assert main(["diagnose", *conf, "model=oscillator", "data=oscillator", "diagnose.plots=false"]) == 0
    sweep = ["sweep", *conf, *TINY, f"sweep.space={space}", "sweep.n_trials=4", "sweep.pruner_startup_trials=2"]
    assert main(sweep) == 0
    capsys.readouterr()
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{user_project / 'mlflow.db'}", "experiment": "physmend"}))
    client = store.client

    # the listing: JSON and text
    assert main(["runs", "--json", *conf]) == 0
    data = json.loads(capsys.readouterr().out)
    (sw,) = data["sweeps"]
    states = [t["state"] for t in sw["trials"]]
    assert states == ["COMPLETE", "COMPLETE", "FAIL", "PRUNED"]
    good = [t for t in sw["trials"] if t["state"] == "COMPLETE"]
    best = min(good, key=lambda t: t["val_rmse"])
    other = next(t for t in good if t is not best)
    failed, pruned = sw["trials"][2], sw["trials"][3]
    assert best["selected"] and best["best"] and sw["selected_by"] == "auto" and sw["current"]
    assert data["current_selection"] == best["run_id"] == sw["best_run_id"]
    assert [r["stage"] for r in data["stage_runs"]] == ["diagnose"]
    assert "TrainingDiverged" in failed["error"]
    assert main(["runs", *conf]) == 0
    text = capsys.readouterr().out
    best_line = next(line for line in text.splitlines() if best["run_id"] in line and "COMPLETE" in line)
    assert best_line.lstrip().startswith("*+")
    assert "FAIL" in text and "PRUNED" in text and "diagnose" in text and "physmend select RUN_ID" in text
    assert main(["runs", "--sweep", sw["run_id"], "--json", *conf]) == 0
    assert json.loads(capsys.readouterr().out)["stage_runs"] == []
    assert main(["runs", "--sweep", best["run_id"], *conf]) == 2
    assert "must be a 'sweep' run, but is a 'trial' run" in capsys.readouterr().err

    # bad run IDs: one clear error each, nothing changes
    other_exp = client.create_experiment("elsewhere")
    foreign = client.create_run(other_exp).info.run_id
    client.set_terminated(foreign)
    fake = client.create_run(store.experiment_id, tags={"physmend.stage": "trial", "physmend.trial_state": "COMPLETE",
                                                         "physmend.trial_number": "99", "mlflow.parentRunId": sw["run_id"]})
    client.set_terminated(fake.info.run_id)
    diagnose_id = data["stage_runs"][0]["run_id"]
    before = snapshot(client)
    cases = {
        "0123456789abcdef0123456789abcdef": "does not exist in the tracking store",
        foreign: "belongs to another MLflow experiment",
        sw["run_id"]: "is a 'sweep' run, not a sweep trial",
        diagnose_id: "is a 'diagnose' run, not a sweep trial",
        failed["run_id"]: "must have finished training to be selected, but its run is FAILED and the trial FAIL",
        pruned["run_id"]: "its run is KILLED and the trial PRUNED",
        fake.info.run_id: "has no model artifacts ['model/hybrid.json', 'model/weights.pt']",
    }
    for run_id, message in cases.items():
        assert main(["select", run_id, *conf]) == 2, run_id
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert snapshot(client) == before
    with pytest.raises(TrackingError, match="the trial FAIL"):
        load_trial(store, failed["run_id"])

    # a person's choice: three tags on the sweep run, and the names the MLflow UI shows (the chosen
    # trial marked ▶, the best keeps its ★), nothing else
    assert main(["select", other["run_id"], *conf]) == 0
    out = capsys.readouterr().out
    assert other["run_id"] in out and f"was {best['run_id']}" in out
    after = snapshot(client)
    names = {"mlflow.runName", "physmend.marked"}

    def unnamed(runs: dict[str, Any]) -> dict[str, Any]:
        return {r: (st, {k: v for k, v in tags.items() if k not in names}, pa, me) for r, (st, tags, pa, me) in runs.items()}

    parent_before, parent_after = before.pop(sw["run_id"]), after.pop(sw["run_id"])
    assert unnamed(after) == unnamed(before)
    assert after[other["run_id"]][1]["mlflow.runName"].startswith("▶ trial-") and "(selected)" in after[other["run_id"]][1]["mlflow.runName"]
    assert after[best["run_id"]][1]["mlflow.runName"].startswith("★ trial-") and after[best["run_id"]][1]["mlflow.runName"].endswith("(best)")
    changed = {k for k in parent_after[1] if parent_after[1][k] != parent_before[1].get(k)}
    assert changed == {"physmend.selected_run_id", "physmend.selected_by", "physmend.selected_at", "mlflow.runName"}
    assert "▶ trial-" in parent_after[1]["mlflow.runName"] and parent_after[1]["mlflow.runName"].startswith("★ ")
    tags = parent_after[1]
    assert tags["physmend.selected_run_id"] == other["run_id"] and tags["physmend.best_run_id"] == best["run_id"]
    assert tags["physmend.selected_by"] == getpass.getuser()
    assert tags["physmend.selected_at"] > parent_before[1]["physmend.selected_at"]
    assert parent_after[0] == parent_before[0]
    assert current_selection(store) == other["run_id"]
    assert load_trial(store).cfg.train.lr == 0.005

    # the listing shows the person's choice and the automatic best apart
    assert main(["runs", "--json", *conf]) == 0
    trials = {t["run_id"]: t for t in json.loads(capsys.readouterr().out)["sweeps"][0]["trials"]}
    assert trials[other["run_id"]]["selected"] and not trials[other["run_id"]]["best"]
    assert trials[best["run_id"]]["best"] and not trials[best["run_id"]]["selected"]
