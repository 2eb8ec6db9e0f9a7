"""What a user sees of a sweep on a real MLflow tracking server (``mlflow server`` on an sqlite store
in a temporary folder): the sweep's output carries no MLflow console line (MLflow prints two per
run there by default; every stage's runs end the same way, so a discover prints none either — the
line count of a 20-trial sweep is tests/sweep/test_output.py), and MLflow's own UI, opened in a
real headless browser, answers "which trial is best" — in its
default runs table (the sweep run's name) and in the saved view physmend writes (the trials
ranked by ``val.rmse``, the column shown). Screenshots go to ``$PHYSMEND_SCREENSHOTS`` when set
(``benchmarks/screenshots/`` holds the committed ones), else to the test's temporary folder.
The browser part skips only where no Chromium is installed.
"""

from __future__ import annotations

import html
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared helpers  # noqa: E402
from mlflow_servers import mlflow_server  # noqa: E402

N_TRIALS = 3
TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=2", "train.eval_every=1", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.space=small", f"sweep.n_trials={N_TRIALS}", "sweep.group=3", "train.polish=0", "train.warm_start=none", "sweep.pruner=none", "sweep.figures=false",
]
#: what MLflow itself prints: run/experiment links at each run's end, its loggers' notices
MLFLOW_LINES = ("View run", "View experiment", "🏃", "🧪", " INFO mlflow", "mlflow.tracking", "mlflow.store")


@pytest.fixture
def tracking_server(tmp_path: Path) -> Iterator[str]:
    """``mlflow server`` on an sqlite store with proxied artifacts: yields its URL."""
    folder = tmp_path / "server"
    folder.mkdir()
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    with mlflow_server(f"sqlite:///{folder / 'mlflow.db'}", folder / "artifacts", folder, folder / "server.log", env) as url:
        yield url


def _browse(chromium: str, address: str, shot: Path) -> str:
    """The page's DOM after its scripts ran (MLflow's UI is a single-page app), and a screenshot."""
    shot.parent.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=10000",
         "--window-size=1600,1000", f"--screenshot={shot}", "--dump-dom", address],
        capture_output=True, text=True, timeout=120)
    assert shot.exists() and shot.stat().st_size > 10_000, done.stderr[-2000:]
    return html.unescape(done.stdout)


@pytest.mark.usefixtures("reset_mlflow")  # tests/conftest.py
def test_a_sweep_on_a_tracking_server_is_quiet_and_its_best_trial_shows_in_the_mlflow_ui(
        user_project: Path, tracking_server: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capfd: pytest.CaptureFixture[str]) -> None:
    from mlflow.tracking import MlflowClient

    from physmend.cli import main

    for key in ("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "MLFLOW_LOGGING_LEVEL"):  # MLflow's defaults, as a user has them
        monkeypatch.delenv(key, raising=False)
    monkeypatch.chdir(user_project)
    rc = main(["sweep", "--config-dir", str(user_project / "my_conf"), *TINY, f"tracking.uri={tracking_server}"])
    out, err = capfd.readouterr()  # file descriptors: what MLflow writes to sys.stdout or its loggers is here too
    assert rc == 0, err[-3000:]
    for line in (out + err).splitlines():
        assert not any(word in line for word in MLFLOW_LINES), line
    assert len(out.splitlines()) < 60 and len(err.splitlines()) < 60, (out, err)
    assert "epoch" in err  # the bar says how far the running trials are
    assert f"{N_TRIALS} of {N_TRIALS} trials" in out and "best: trial" in out and "not final" not in out

    client = MlflowClient(tracking_uri=tracking_server)
    exp = client.get_experiment_by_name("physmend")
    (sweep,) = client.search_runs([exp.experiment_id], "tags.`physmend.stage` = 'sweep'")
    trials = client.search_runs([exp.experiment_id], "tags.`physmend.stage` = 'trial'", max_results=100)
    assert len(trials) == N_TRIALS
    best = min(trials, key=lambda r: r.data.metrics["val.rmse"])
    value = best.data.metrics["val.rmse"]
    number = int(best.data.tags["physmend.trial_number"])
    assert best.info.run_id == sweep.data.tags["physmend.best_run_id"] == sweep.data.tags["physmend.selected_run_id"]
    assert best.info.run_name == f"★ trial-{number:04d} val.rmse={value:.4g} (best, selected)"
    assert sweep.info.run_name.startswith(f"★ #{number} {value:.4g} val.rmse · trial-{number:04d} · sweep ")
    assert sweep.data.metrics["val.rmse"] == pytest.approx(value)  # the sweep run's own metric: the best's
    others = [r for r in trials if r.info.run_id != best.info.run_id]
    assert all(r.info.run_name.startswith("trial-") and "★" not in r.info.run_name for r in others)

    chromium = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)
    if chromium is None:
        pytest.skip("no Chromium on this machine: the check in a real browser is skipped (the output checks passed)")
    shots = Path(os.environ.get("PHYSMEND_SCREENSHOTS", tmp_path / "screenshots"))
    runs = f"{tracking_server}/#/experiments/{exp.experiment_id}/runs"
    # the default runs table (a browser that never changed a column): the sweep run names its best trial
    dom = _browse(chromium, f"{runs}?workflowType=machine_learning", shots / "runs-table-default.png")
    assert sweep.info.run_name in dom, dom[-3000:]
    # the saved view physmend wrote ("Views"; `physmend ui` prints its address): trials by val.rmse
    view = f"{runs}?workflowType=machine_learning&viewStateShareKey=physmend-trials"
    dom = _browse(chromium, view, shots / "runs-table-trials-by-val-rmse.png")
    assert best.info.run_name in dom and repr(value)[:7] in dom, dom[-3000:]
    first_other = min(dom.find(r.info.run_name) for r in others)
    assert -1 < dom.find(best.info.run_name) < first_other  # the best on top, every trial listed
    # MLflow's own way in (home page → experiment) opens its GenAI overview on a fresh browser, whatever
    # the experiment's tags; the description above it links to the runs table
    dom = _browse(chromium, f"{tracking_server}/#/experiments/{exp.experiment_id}", shots / "experiment-default-landing.png")
    assert "runs table: trials ranked by val.rmse" in dom, dom[-3000:]
