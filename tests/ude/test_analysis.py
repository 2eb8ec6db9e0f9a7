"""Correction ranking and input sensitivities on a hybrid with known structure."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude.analysis import input_jacobian, rank_corrections, rank_inputs, training_trajectories
from physmend.ude.train import build_spec, reference
from physmend.ude.hybrid import HybridModel


@pytest.fixture
def hybrid_and_traj(user_project: Path, monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator", "ude.width=8", "ude.depth=1"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    spec = build_spec(cfg, problem, reference(problem, cfg))
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    with torch.no_grad():  # a network whose cart.v output is large and cart.x output tiny
        last = hybrid.net[-1]
        last.weight[spec.corrected.index("cart.x")] *= 1e-4
        last.weight[spec.corrected.index("cart.v")] *= 50.0
    return cfg, problem, hybrid, training_trajectories(hybrid, problem, cfg)


def test_ranking_puts_the_dominant_output_first_and_masking_removes_it(hybrid_and_traj) -> None:  # noqa: ANN001
    cfg, problem, hybrid, traj = hybrid_and_traj
    ranking = rank_corrections(hybrid, traj)
    assert [n for n, _ in ranking] == ["cart.v", "cart.x"]
    assert ranking[0][1] > 100 * ranking[1][1]
    hybrid.keep_only(["cart.x"])
    x = traj.x[:5]
    corr = hybrid.corrections(traj.u[:5], x, traj.p[:5])
    assert torch.all(corr[:, hybrid.spec.corrected.index("cart.v")] == 0)


def test_jacobian_matches_finite_differences(hybrid_and_traj) -> None:  # noqa: ANN001
    _, _, hybrid, traj = hybrid_and_traj
    jac = input_jacobian(hybrid, traj, max_rows=7)
    z = traj.z[torch.linspace(0, traj.z.shape[0] - 1, 7).long()]
    eps = 1e-6
    for j in range(z.shape[1]):
        dz = torch.zeros_like(z)
        dz[:, j] = eps
        fd = (hybrid.corrections_of_z(z + dz) - hybrid.corrections_of_z(z - dz)) / (2 * eps)
        torch.testing.assert_close(jac[:, :, j], fd, rtol=1e-5, atol=1e-10)
    ranked = rank_inputs(hybrid, jac, ["cart.v"])
    assert {n for n, _ in ranked} == set(hybrid.spec.input_names)
