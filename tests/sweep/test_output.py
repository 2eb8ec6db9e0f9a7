"""What a sweep prints: a 20-trial sweep's output stays short (the summary on stdout, one progress
bar on stderr that says which trials train and their epoch), and a worker that ends while another
still trains says its choice is not final; real training in a real MLflow sqlite store and Optuna
study (the user's oscillator of tests/conftest.py, trials trained ten at a time)."""

from __future__ import annotations

from pathlib import Path
import re

import pytest

from physmend.cli import main

N_TRIALS = 20
TINY = [
    "model=oscillator", "data=oscillator", "train.epochs=2", "train.eval_every=1", "train.step=0.1",
    "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
    "sweep.space=small", f"sweep.n_trials={N_TRIALS}", "sweep.group=10", "sweep.pruner=none", "sweep.figures=false",
    "sweep.progress=true", "train.polish=0", "train.warm_start=none",
]

pytestmark = pytest.mark.usefixtures("reset_mlflow")  # tests/conftest.py


def test_a_20_trial_sweep_prints_under_60_lines(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                capfd: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(user_project)
    assert main(["sweep", "--config-dir", str(user_project / "my_conf"), *TINY]) == 0
    out, err = capfd.readouterr()  # file descriptors: whatever any library writes is counted too
    assert len(out.splitlines()) < 60, out
    assert len(err.splitlines()) < 60, err
    assert f"{N_TRIALS} of {N_TRIALS} trials: {N_TRIALS} complete" in out and "best: trial" in out
    assert "not final" not in out and "so far" not in out  # one worker: its choice is final
    # the bar counts epochs inside the trials, not only trials (which epoch it shows depends on when it
    # redraws: at most every bar interval, and a stack's two epochs can take less than that)
    assert re.search(r"trials? \d+(–\d+)? epoch \d/2", err), err

    # another worker's trial still runs (asked here, as that worker would, heartbeat fresh): a worker
    # that ends now prints what it found so far, never a final choice
    import optuna

    study = optuna.load_study(study_name="oscillator-oscillator-small", storage=f"sqlite:///{user_project / 'optuna.db'}")
    study.ask()
    args = [a for a in TINY if not a.startswith("sweep.n_trials=")]
    assert main(["sweep", "--config-dir", str(user_project / "my_conf"), *args, f"sweep.n_trials={N_TRIALS + 1}"]) == 0
    out = capfd.readouterr().out
    assert "best so far: trial" in out and "selected so far: " in out, out
    assert "not final: 1 trial(s) still running in other workers; the last worker to finish records the final choice" in out
