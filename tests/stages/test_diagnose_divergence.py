"""physmend diagnose on models as written that diverge: the divergence is the finding (which state,
from when in the data's own time unit, against the records), exit 0, with a real MLflow store."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the users' projects  # noqa: E402
from diverging_projects import write_project  # noqa: E402
from physmend.cli import main  # noqa: E402


def _diagnose(root: Path, kind: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, dict]:
    from mlflow.tracking import MlflowClient

    conf, name = write_project(root, kind)
    rc = main(["diagnose", "--config-dir", str(conf), f"model={name}", f"data={name}", "diagnose.plots=false"])
    out = capsys.readouterr().out
    client = MlflowClient(tracking_uri=f"sqlite:///{root / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("physmend").experiment_id])
    assert len(runs) == 1
    path = client.download_artifacts(runs[0].info.run_id, "diagnosis.json", str(root))
    return rc, out, {"json": json.loads(Path(path).read_text()), "metrics": runs[0].data.metrics}


def test_growth_without_bound_is_reported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, reset_mlflow) -> None:  # noqa: ANN001
    monkeypatch.chdir(tmp_path)
    rc, out, run = _diagnose(tmp_path, "growth", capsys)
    assert rc == 0, out
    line = next(l for l in out.splitlines() if l.startswith("**The model as written diverges.**"))
    assert "colony.x" in line and "leaves the range of the records" in line and " d " in line and "reaches" in line
    found = run["json"]["divergence"]
    assert {d["experiment"] for d in found} == {"e1", "e2", "e3"}
    assert all(d["name"] == "colony.x" and not d["blows_up"] and 5.0 < d["time"] < 15.0 for d in found)
    assert 5.0 < run["metrics"]["diverges_at.e1"] < 15.0


def test_a_finite_time_blow_up_is_reported_not_an_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys, reset_mlflow) -> None:  # noqa: ANN001
    monkeypatch.chdir(tmp_path)
    rc, out, run = _diagnose(tmp_path, "blowup", capsys)
    assert rc == 0, out  # was: exit 2, 'step size underflow (9.07e-14 s)'
    assert "blows up in finite time" in out and "fuel.x" in out and " tu " in out
    assert "step size underflow" not in out
    by_exp = {d["experiment"]: d for d in run["json"]["divergence"]}
    assert all(d["blows_up"] and d["peak"] is None for d in by_exp.values())  # peak: infinite (JSON null)
    assert 1.6 < by_exp["e1"]["time"] <= 2.1  # dx/dt = a·x² from 1 blows up at 1/a = 2 tu
    # the table still has every experiment (the model held at the edge of the records' box after)
    assert {f["experiment"] for f in run["json"]["fits"]} == {"e1", "e2", "e3"}
