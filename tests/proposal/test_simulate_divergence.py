"""``propose`` simulates the model as written and the corrected one on every experiment: a model that
blows up there is reported (held at the edge of its records' range), never a failed stage."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the users' projects  # noqa: E402
from diverging_projects import write_project  # noqa: E402


def test_a_model_that_blows_up_is_simulated_and_its_divergence_reported(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from physmend.config import compose
    from physmend.problem import load_problem
    from physmend.proposal.fits import simulate

    monkeypatch.chdir(tmp_path)
    conf, name = write_project(tmp_path, "blowup")
    cfg = compose([f"model={name}", f"data={name}"], user_config_dir=conf)
    problem = load_problem(cfg)
    batch, traj, diverged = simulate(problem, cfg)
    assert traj.outputs.shape[:2] == batch.obs.shape[:2]
    assert bool(torch.isfinite(traj.outputs).all())  # held inside the box: a table and plots all the same
    assert diverged and all(d.blows_up for d in diverged)
    assert {d.experiment for d in diverged} == {e.id for e in problem.experiments}
    text = diverged[0].describe(problem.time_unit, "")
    assert problem.time_unit in text
