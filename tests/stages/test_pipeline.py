"""The whole pipeline on a user's own non-thermal model, through the CLI, with real stores:
sweep → mask → sensitivity → symbolic → propose → accept / reject, and clear errors for bad IDs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from physmend.cli import main

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=40",
        "train.eval_every=20", "simulate.rtol=1e-6", "simulate.atol=1e-7", "ude.depth=1"]


def _run(project: Path, capsys, *args: str) -> tuple[int, str, str]:  # noqa: ANN001
    rc = main([args[0], "--config-dir", str(project / "my_conf"), *args[1:], *TINY])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _last_run_id(text: str, stage: str) -> str:
    line = next(l for l in reversed(text.splitlines()) if l.startswith(f"{stage} run: "))
    return line.split()[2]


@pytest.mark.slow
def test_pipeline_end_to_end_on_a_user_model(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(user_project)
    rc, out, err = _run(user_project, capsys, "sweep", "sweep.space=small", "sweep.n_trials=1")
    assert rc == 0, err
    rc, out, err = _run(user_project, capsys, "mask", "mask.max_k=2")
    assert rc == 0, err
    # the network corrects cart.v only (der(x) = v is a definition): the kept set is its own, not retrained
    assert "goes on as it is" in out and "Retrained with" not in out, out
    mask_id = _last_run_id(out, "mask")
    rc, out, err = _run(user_project, capsys, "sensitivity", mask_id)
    assert rc == 0, err
    sens_id = _last_run_id(out, "sensitivity")
    rc, _, err = _run(user_project, capsys, "sensitivity", mask_id, "sensitivity.group_r=2")
    assert rc == 2 and "sensitivity.group_r must be a number in (0, 1], but got 2" in err  # checked at compose
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "symbolic.window=-5")
    assert rc == 2 and "symbolic.window must be 'auto' or a number > 0, but got -5" in err
    # a Pareto index out of range is a clear error naming the rule
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "+symbolic.choice={cart.v: 999}", "symbolic.refit_epochs=0")
    assert rc == 2 and "Pareto index must be in [0," in err and "but got 999" in err
    # a choice for an equation that was not kept is a clear error, not silently ignored
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "+symbolic.choice={cart.a: 0}", "symbolic.refit_epochs=0")
    assert rc == 2 and "symbolic.choice names ['cart.a'], but the formulas are for the kept corrections [" in err
    rc, out, err = _run(user_project, capsys, "symbolic", sens_id, "symbolic.refit_epochs=20")
    assert rc == 0, err
    sym_id = _last_run_id(out, "symbolic")
    rc, out, err = _run(user_project, capsys, "propose", sym_id)
    assert rc == 0, err
    prop_id = _last_run_id(out, "propose")
    assert "## Equations corrected" in out and "| run3 | test | cart.x |" in out
    client = MlflowClient(tracking_uri=f"sqlite:///{user_project / 'mlflow.db'}")
    proposal = json.loads(Path(client.download_artifacts(prop_id, "proposal.json", str(user_project))).read_text())
    after = {r["experiment"]: r["after"] for r in proposal["rows"]}
    # held-out experiment improves over the model as written
    test_row = next(r for r in proposal["rows"] if r["role"] == "test")
    assert test_row["after"] < test_row["before"]
    assert {"report.md", "report.html", "corrections.yaml"} <= {a.path for a in client.list_artifacts(prop_id)}

    # reject changes nothing but tags
    before_files = sorted(p.name for p in user_project.iterdir())
    rc, out, err = _run(user_project, capsys, "reject", prop_id, "decide.reason=not convinced")
    assert rc == 0, err
    assert sorted(p.name for p in user_project.iterdir()) == before_files
    tags = client.get_run(prop_id).data.tags
    assert tags["physmend.decision"] == "rejected" and tags["physmend.reject_reason"] == "not convinced"
    rc, _, err = _run(user_project, capsys, "accept", prop_id)
    assert rc == 2 and "already rejected" in err

    # a fresh proposal from the same symbolic run, accepted: the written model reproduces the fit
    rc, out, err = _run(user_project, capsys, "propose", sym_id)
    prop2 = _last_run_id(out, "propose")
    rc, out, err = _run(user_project, capsys, "accept", prop2)
    assert rc == 0, err
    written = next((user_project / "corrections").glob("oscillator-*.yaml"))
    assert prop2 in written.read_text()
    rc, out, err = _run(user_project, capsys, "diagnose", f"++model.corrections={written}")
    assert rc == 0, err
    diag_id = _last_run_id(out, "diagnose")
    metrics = client.get_run(diag_id).data.metrics
    for exp, rmse in after.items():
        assert metrics[f"rmse.{exp}.cart.x"] == pytest.approx(rmse, rel=1e-6)


def test_bad_run_ids_are_clear_errors(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    rc, out, err = _run(user_project, capsys, "diagnose")
    diag_id = _last_run_id(out, "diagnose")
    rc, _, err = _run(user_project, capsys, "mask", diag_id)
    assert rc == 2 and f"run {diag_id!r} must be a 'trial' run, but is a 'diagnose' run" in err
    rc, _, err = _run(user_project, capsys, "sensitivity", "0" * 32)
    assert rc == 2 and "does not exist" in err
    rc, _, err = _run(user_project, capsys, "propose")
    assert rc == 2 and "no finished 'symbolic' run" in err
    rc, _, err = _run(user_project, capsys, "accept", diag_id)
    assert rc == 2 and "must be a 'propose' run" in err
    rc, _, err = _run(user_project, capsys, "mask")
    assert rc == 2 and "no trial is selected" in err


def test_discover_rejects_a_bad_group_shapes_before_writing_anything(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    before = sorted(p.name for p in user_project.iterdir())
    rc, _, err = _run(user_project, capsys, "discover", "discover.group_shapes=no")
    assert rc == 2
    assert "discover.group_shapes must be true or false, but got 'no'" in err
    assert sorted(p.name for p in user_project.iterdir()) == before  # no MLflow store, no runs
