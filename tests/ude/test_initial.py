"""Initial values a data config declares unknown (``initial: {state: [low, high]}``) are estimated
from the opening of each record, by the model as written and by every hybrid alike, and trained as
segment starts within their range."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.simulate import make_batch
from physmend.simulate.initial import estimate_initial
from physmend.ude import reference, train
from physmend.ude.metrics import hybrid_states
from physmend.ude.reference import solver_options, simulate_with
from physmend.ude.shooting import pinned_starts
from physmend.ude.shooting import plan_shooting

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=10",
        "train.eval_every=10", "train.lr=0.02", "ude.width=8", "ude.depth=1", "train.patience=0",
        "simulate.rtol=1e-6", "simulate.atol=1e-7"]
TRUE_X0 = [0.5, -0.3, 0.2]  # cart.x0 of run1..run3 in the fixture (tests/conftest.py); every record starts at rest
TRUE_DRAG = 0.9  # the fixture truth's quadratic drag, N/(m/s)^2


def _unknown_starts(project: Path) -> None:
    """Rewrite the data config: no experiment states its start; both states lie in [-1, 1]."""
    path = project / "my_conf" / "data" / "oscillator.yaml"
    text = re.sub(r"parameters: \{cart\.x0: [-0-9.]+\}",
                  "parameters: {cart.x0: 0.0}\n    initial: {cart.x: [-1.0, 1.0], cart.v: [-1.0, 1.0]}",
                  path.read_text())
    assert text.count("initial:") == 3
    path.write_text(text)


def test_unknown_initial_values_are_estimated_from_each_record(user_project: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    _unknown_starts(user_project)
    cfg = compose(TINY, user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    assert batch.initial_ranges[0] == {"cart.x": (-1.0, 1.0), "cart.v": (-1.0, 1.0)}
    assert batch.u0[:, :2].abs().max() == 0.0  # mid-range until estimated

    ref = reference(problem, cfg)
    # the model as written (no drag) fitted on the opening of each record: a start inside the range
    # (biased: the missing drag pulls it), every record simulated from it
    assert bool((ref.batch.u0[:, :2].abs() <= 1.0).all()) and bool(torch.isfinite(ref.states).all())

    # training: an unknown first-segment entry is trained, clamped to its range; known ones are pinned
    plan = plan_shooting(problem, ref.batch, cfg)
    pinned, lo, hi = pinned_starts(ref.batch, plan, problem.compiled.state_names)
    first = plan.first
    assert not bool(pinned.any())  # later segments are free anyway; every first one declares its start unknown
    assert bool((lo[first] == -1.0).all()) and bool((hi[first] == 1.0).all())
    assert bool(torch.isinf(lo[~first]).all())

    result = train(cfg, problem)
    states = hybrid_states(result.hybrid, problem, make_batch(problem.experiments, problem.compiled, problem.dtype),
                           solver_options(cfg))
    # the hybrid's own estimates (not the written model's), inside the declared range
    assert bool((states[0, :, :2].abs() <= 1.0).all())
    assert not torch.allclose(states[0], ref.batch.u0)
    assert result.metrics["test.failed"] == 0.0 and torch.isfinite(torch.tensor(result.metrics["test.rmse"]))


def test_with_the_physics_complete_the_true_starts_are_found(user_project: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The search itself: a model that lacks nothing (the fixture's truth, drag included) recovers
    each record's start, position and velocity, from its opening alone."""
    monkeypatch.chdir(user_project)
    _unknown_starts(user_project)
    cfg = compose(TINY, user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    sim = solver_options(cfg)

    def truth(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        pos, vel = u[..., 0], u[..., 1]
        acc = (x[..., 0] - 8.0 * pos - 0.4 * vel - TRUE_DRAG * vel * vel.abs()) / 2.0
        return torch.stack([vel, acc], -1)

    def outputs(sub, u0):  # noqa: ANN001, ANN202
        return simulate_with(truth, sub, u0, sim)[..., :1]

    u0 = estimate_initial(outputs, batch, problem.compiled.state_names)
    expected = torch.tensor([[x0, 0.0] for x0 in TRUE_X0], dtype=u0.dtype)
    # position to 1 cm, velocity to 2 cm/s: what 3 mm noise on a 3 s opening allows
    torch.testing.assert_close(u0[:, 0], expected[:, 0], rtol=0, atol=0.01)
    torch.testing.assert_close(u0[:, 1], expected[:, 1], rtol=0, atol=0.02)
    # about an earlier estimate (a hybrid's previous checkpoint): 3 local rounds instead of 7, same answer
    calls: list[int] = []

    def counted(sub, start):  # noqa: ANN001, ANN202
        calls.append(sub.size)
        return outputs(sub, start)

    again = estimate_initial(counted, batch, problem.compiled.state_names, near=u0 + 0.01)
    assert len(calls) == 3
    torch.testing.assert_close(again[:, 0], expected[:, 0], rtol=0, atol=0.01)
    torch.testing.assert_close(again[:, 1], expected[:, 1], rtol=0, atol=0.02)


def test_a_failing_candidate_scores_infinitely_badly_and_a_batch_without_unknowns_is_untouched(
        user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from physmend.simulate import SimulationError

    monkeypatch.chdir(user_project)
    cfg = compose(TINY, user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    calls: list[int] = []

    def never(sub, u0):  # noqa: ANN001, ANN202
        calls.append(sub.size)
        raise SimulationError("not reached")

    assert torch.equal(estimate_initial(never, batch, problem.compiled.state_names), batch.u0) and not calls

    _unknown_starts(user_project)
    cfg = compose(TINY, user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    assert all(batch.initial_ranges)
    sim = solver_options(cfg)
    model = problem.compiled
    def positive_only(sub, u0):  # noqa: ANN001, ANN202
        """The model as written, except that a start with cart.x < 0 'fails to simulate'."""
        if bool((u0[:, 0] < 0).any()):
            raise SimulationError("negative start")
        states = simulate_with(model.bind(sub.params), sub, u0, sim, model.jacobian(sub.params))
        return model.outputs(states, sub.inputs.at(sub.t), sub.params[None])

    u0 = estimate_initial(positive_only, batch, model.state_names)
    assert float(u0[0, 0]) == pytest.approx(TRUE_X0[0], abs=0.03)  # run1 starts at +0.5: found
    assert float(u0[1, 0]) >= 0.0  # run2 starts at -0.3: every candidate below 0 failed, never chosen
    with pytest.raises(SimulationError, match="negative start"):
        estimate_initial(positive_only, batch, model.state_names, isolate=False)
