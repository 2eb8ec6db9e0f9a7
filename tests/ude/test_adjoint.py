"""The training solve with the hand-written backward pass (:mod:`physmend.ude.adjoint`) gives
autograd's trajectories and gradients: gradcheck in float64 on a small stacked problem of every
shape it takes (state subsets, corrected subsets, the box, every activation), and the drive solve
of a real hybrid model (one and several experiments' matrices, subsets, both correction units, an
estimated parameter) against :func:`rk4_segments` with :func:`hybrid_drive`."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.ude.adjoint import ACTIVATIONS, adjoint_applies, hybrid_solve, rk4_adjoint
from physmend.ude.drive import hybrid_drive
from physmend.ude.shooting import BOX_MARGIN, rk4_segments

from tests.ude.test_drive import VARIANTS, _setup
from tests.ude.test_stacked import _cfg, short_project  # noqa: F401 - the fixture

DT = torch.float64


def _problem(M: int = 2, S: int = 3, n: int = 3, h1: int = 4, h2: int = 3, K: int = 3, reads: list[int] | None = None,
             index: list[int] | None = None, box: bool = True) -> tuple[list[torch.Tensor], dict]:
    g = torch.Generator().manual_seed(1)
    r = n if reads is None else len(reads)
    k = n if index is None else len(index)

    def rnd(*shape: int, scale: float = 1.0) -> torch.Tensor:
        return (scale * torch.randn(*shape, dtype=DT, generator=g)).requires_grad_()

    tensors = [rnd(M * S, n), rnd(M * S, n, n, scale=0.3), rnd(2 * K + 1, M * S, n), rnd(2 * K + 1, M, S, h1),
               rnd(M, r, h1, scale=0.5), (torch.rand(M, S, k, dtype=DT, generator=g) + 0.5).requires_grad_(),
               rnd(M, h1, h2, scale=0.5), rnd(M, 1, h2), rnd(M, h2, k, scale=0.5), rnd(M, 1, k)]
    kw = {"h": 0.1, "steps": K, "box": (torch.full((n,), -1.5, dtype=DT), torch.full((n,), 1.5, dtype=DT)) if box else None,
          "reads": None if reads is None else torch.tensor(reads), "index": None if index is None else torch.tensor(index)}
    return tensors, kw


def _call(activation: str, kw: dict):  # noqa: ANN202
    def f(u0, A, d, pre, wu, gain, w1, b1, w2, b2):  # noqa: ANN001, ANN202, PLR0913
        return rk4_adjoint(u0, A, d, pre, wu, [(w1, b1), (w2, b2)], gain, activation=activation, **kw)
    return f


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_gradcheck_every_activation(activation: str) -> None:
    tensors, kw = _problem(box=False)
    assert torch.autograd.gradcheck(_call(activation, kw), tensors, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_one_activation_per_model() -> None:
    """A stack whose models have different activations (a sweep group's trials) is one solve, each
    model with its own: autograd's gradients, and each model's rows the trajectory it has alone."""
    from physmend.ude import adjoint

    mixed = ("gelu", "tanh", "tanh", "softplus")
    tensors, kw = _problem(M=4, S=2, box=False)
    before = adjoint.LOOPS["compiled"]
    adjoint.LOOPS["compiled"] = False  # the torch loops (test_rk4_loops.py holds the compiled ones to them)
    try:
        assert torch.autograd.gradcheck(_call(mixed, kw), tensors, eps=1e-6, atol=1e-7, rtol=1e-5)
    finally:
        adjoint.LOOPS["compiled"] = before
    with torch.no_grad():
        traj = _call(mixed, kw)(*tensors)
        for name in set(mixed):
            alone = _call(name, kw)(*tensors)
            rows = [r for r in range(8) if mixed[r // 2] == name]
            torch.testing.assert_close(traj[:, rows], alone[:, rows], rtol=1e-13, atol=1e-13)
            assert not torch.allclose(traj, alone)  # the other models' rows are not this activation's
    with pytest.raises(ValueError, match="one activation per model is needed \\(4 models\\), but got"):
        _call(mixed[:3], kw)(*tensors)


@pytest.mark.parametrize("shape", [{"reads": [0, 2], "index": [1]}, {"M": 1, "S": 2}, {"box": True}],
                         ids=["subsets", "one-model", "box"])
def test_gradcheck_shapes(shape: dict) -> None:
    tensors, kw = _problem(**shape)
    if kw["box"] is not None:  # some stage states outside the box, none on its edge (clamp has a kink there)
        with torch.no_grad():
            tensors[0].mul_(0.8)
    assert torch.autograd.gradcheck(_call("tanh", kw), tensors, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_the_box_holds_states_as_the_autograd_solve_does() -> None:
    tensors, kw = _problem(K=6)
    with torch.no_grad():
        tensors[2].mul_(20.0)  # drives that push states against the box
    out = _call("tanh", kw)(*tensors)[1:]  # the starts are given, not held
    lo, hi = kw["box"]
    assert bool(((out == lo) | (out == hi)).any())  # held at the box somewhere
    assert bool((out >= lo).all() and (out <= hi).all())


@pytest.mark.parametrize("extra", VARIANTS, ids=["default", "state-units", "subsets", "no-inputs-deep"])
def test_the_hybrid_solve_is_the_drive_solve(user_project: Path, monkeypatch: pytest.MonkeyPatch, extra: list[str]) -> None:
    monkeypatch.chdir(user_project)
    _, problem, ref, hybrid, plan, u0 = _setup(user_project, extra)
    assert adjoint_applies(hybrid) and hybrid.spec.estimated == ["damper.c"]
    box = hybrid.spec.box(BOX_MARGIN, problem.dtype)
    start = u0.clone().requires_grad_()

    def grads(solve: str, per_experiment: bool) -> tuple[torch.Tensor, list[torch.Tensor]]:
        hybrid.zero_grad(set_to_none=True)
        start.grad = None
        p = hybrid.parameters_for(ref.batch.params)
        rows = plan.exp_index if per_experiment else None
        if not per_experiment:
            p = p[plan.exp_index]
        if solve == "adjoint":
            traj = hybrid_solve(hybrid, p, start, plan, box, rows)
        else:
            rhs, drives = hybrid_drive(hybrid, p, plan.x_half, rows)
            traj = rk4_segments(rhs, start, plan, box, drives)
        (traj.pow(2).sum() + traj[-1, :, 0].sum()).backward()
        return traj.detach(), [q.grad.clone() for q in hybrid.parameters()] + [start.grad.clone()]

    for per_experiment in (False, True):
        want_traj, want = grads("autograd", per_experiment)
        got_traj, got = grads("adjoint", per_experiment)
        torch.testing.assert_close(got_traj, want_traj, rtol=1e-12, atol=1e-12)
        assert len(got) == len(want) >= 5
        for a, b in zip(got, want):
            assert float(b.abs().max()) > 0
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_training_with_the_adjoint_is_training_with_autograd(short_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``train.backward: adjoint`` trains the same models as autograd, alone and in a stack (the
    gradients agree to rounding; a few epochs of Adam keep them within ~1e-9), a stack of models
    with different activations included."""
    from physmend.problem import load_problem
    from physmend.ude import TrainResult, train
    from physmend.ude.adjoint import STATS
    from physmend.ude.stack import train_stack
    from physmend.ude.warmstart import forget_warm_starts

    monkeypatch.chdir(short_project)
    trials = [["seed=1", "ude.width=8", "ude.depth=2", "ude.activation=tanh", "train.lr=0.02"],
              ["seed=2", "ude.width=12", "ude.depth=2", "ude.activation=tanh", "train.lr=0.01"],
              ["seed=3", "ude.width=8", "ude.depth=2", "ude.activation=gelu", "train.lr=0.01"]]

    def run(backward: str) -> list[TrainResult]:
        forget_warm_starts()
        cfgs = [_cfg(short_project, *t, f"train.backward={backward}") for t in trials]
        problem = load_problem(cfgs[0])
        return [train(cfgs[0], problem), *train_stack(cfgs, problem, figures=False)]

    before = STATS["solves"]
    want = run("autograd")
    assert STATS["solves"] == before  # autograd: not used
    got = run("adjoint")
    assert STATS["solves"] == before + 2 * 4  # every epoch (train.epochs=4) of the single model and of the (mixed) stack
    for a, b in zip(got, want):
        assert isinstance(a, TrainResult) and isinstance(b, TrainResult)
        ours, theirs = a.hybrid.state_dict(), b.hybrid.state_dict()
        for key in theirs:
            torch.testing.assert_close(ours[key], theirs[key], rtol=1e-8, atol=1e-11, msg=key)
        assert a.val_rmse == pytest.approx(b.val_rmse, rel=1e-8)
    # the shipped default is the adjoint (the seventh proving pass: the same formulas on every example)
    assert _cfg(short_project, *trials[0]).train.backward == "adjoint"
