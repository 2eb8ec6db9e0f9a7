"""Correction ranking and input sensitivities on a hybrid with known structure."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude.analysis import input_jacobian, rank_corrections, rank_inputs, training_trajectories
from physmend.ude.spec import build_spec
from physmend.ude.reference import reference
from physmend.ude.hybrid import HybridModel


@pytest.fixture
def hybrid_and_traj(user_project: Path, monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator", "ude.width=8", "ude.depth=1", "ude.corrected=[cart.x,cart.v]"],
                  user_config_dir=user_project / "my_conf")
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


def test_look_alike_inputs_are_ranked_as_one_group_represented_by_the_measured_one(hybrid_and_traj) -> None:  # noqa: ANN001
    """A network that splits its dependence on x between x and a copy of x (here: −x, the input
    column overwritten) loses to v input by input, but as a group along x's direction it wins."""
    from physmend.ude.analysis import group_inputs, rank_groups

    _, _, hybrid, traj = hybrid_and_traj
    names = hybrid.spec.input_names
    ix, iv, i_f = names.index("cart.x"), names.index("cart.v"), names.index("motor.F")
    traj.z[:, i_f] = -traj.z[:, ix] + 1e-3 * torch.randn(traj.z.shape[0], dtype=traj.z.dtype)
    groups = group_inputs(hybrid, traj, ["cart.x"], 0.98, ["cart.v", "motor.F", "cart.x"])
    by_rep = {g.representative: g for g in groups}
    assert set(by_rep) == {"cart.x", "cart.v"}
    assert by_rep["cart.x"].members == ["cart.x", "motor.F"] and by_rep["cart.x"].signs == [1.0, -1.0]
    jac = torch.zeros(10, len(hybrid.spec.corrected), len(names), dtype=traj.z.dtype)
    jac[..., ix], jac[..., i_f], jac[..., iv] = 1.0, -1.0, 1.5  # d/dx of the shared direction: 1 + 1
    assert rank_inputs(hybrid, jac)[0][0] == "cart.v"
    ranked = rank_groups(hybrid, jac, groups)
    assert [g.representative for g, _ in ranked] == ["cart.x", "cart.v"]
    assert ranked[1][1] == pytest.approx(0.75)
    # no grouping below the threshold: every input its own group
    assert len(group_inputs(hybrid, traj, ["cart.x"], 1.01, names)) == len(names)


def test_the_symbolic_target_hands_back_what_an_estimate_absorbed(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A jointly estimated damper coefficient moved from its declared 0.4 to 2.4 N·s/m (40 % of its
    range 0–5: it may have absorbed missing physics), and a network that adds nothing: the target of
    the velocity equation (N, the units of ``mass·der(v) = …``) is the whole change of that equation
    against the model as written, −(2.4 − 0.4)·v. A small move (to 0.9, 10 %) with a network
    correction far larger than what it changed is calibration: kept, not handed back; the same move
    with no correction to speak of has absorbed the missing term: handed back."""
    from physmend.ude.analysis import equation_corrections

    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator", "ude.width=4", "ude.depth=1"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, reference(problem, cfg)), problem.dtype)
    assert hybrid.spec.estimated == ["damper.c"] and hybrid.spec.corrected == ["cart.v"]  # der(x) = v: a definition
    with torch.no_grad():
        hybrid.net[-1].weight.zero_()
        hybrid.net[-1].bias.zero_()
        lo, hi = hybrid.est_lo, hybrid.est_hi
        hybrid.est_raw.copy_(torch.logit((torch.tensor([2.4], dtype=lo.dtype) - lo) / (hi - lo)))
    traj = training_trajectories(hybrid, problem, cfg)
    assert traj.corr.abs().max() == 0
    target = equation_corrections(hybrid, problem, traj, ["cart.v"])[:, 0]
    v = traj.u[:, problem.model.state_names.index("cart.v")]
    assert torch.allclose(target, -2.0 * v, atol=1e-9)
    with torch.no_grad():
        hybrid.est_raw.copy_(torch.logit((torch.tensor([0.9], dtype=lo.dtype) - lo) / (hi - lo)))
    traj = training_trajectories(hybrid, problem, cfg)
    assert traj.handed == ["damper.c"]  # no correction at all: the move is all there is
    target = equation_corrections(hybrid, problem, traj, ["cart.v"])[:, 0]
    v = traj.u[:, problem.model.state_names.index("cart.v")]
    assert torch.allclose(target, -0.5 * v, atol=1e-9)
    with torch.no_grad():  # a network correction ~100x what the move changed: calibration, kept
        hybrid.net[-1].bias.fill_(50.0)
    traj = training_trajectories(hybrid, problem, cfg)
    assert traj.handed == [] and bool(traj.corr.abs().min() > 0)
    assert torch.equal(traj.added, traj.corr)  # the target is the network's correction alone

