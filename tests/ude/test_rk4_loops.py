"""The compiled time loops of the training solve (:mod:`physmend.ude.rk4_loops`) give the torch
loops' trajectories and gradients (:class:`physmend.ude.adjoint._Solve`, itself checked against
autograd in test_adjoint.py) on every shape they take; the threaded loops give the serial ones'
numbers exactly; reused buffers never leak one solve's values into another's. The activations
themselves: test_vector_math.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physmend.ude import adjoint, compiled_solve
from physmend.ude.adjoint import ACTIVATIONS

from tests.ude.test_adjoint import _call, _problem


def _solve(activation: str, tensors: list[torch.Tensor], kw: dict, *, compiled: bool, threads: int = 1,
           weight: torch.Tensor | None = None) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The trajectory and the gradient of every input of ``sum(w·traj²)`` with the compiled or torch loops."""
    before = (adjoint.LOOPS["compiled"], torch.get_num_threads())
    adjoint.LOOPS["compiled"] = compiled
    torch.set_num_threads(threads)
    try:
        for t in tensors:
            t.grad = None
        traj = _call(activation, kw)(*tensors)
        w = torch.ones_like(traj) if weight is None else weight
        (w * traj.pow(2)).sum().backward()
        return traj.detach(), [t.grad.clone() for t in tensors]
    finally:
        adjoint.LOOPS["compiled"], _ = before
        torch.set_num_threads(before[1])


SHAPES = [{}, {"reads": [0, 2], "index": [1]}, {"index": [2, 0, 1]}, {"M": 1, "S": 4}, {"box": False},
          {"M": 3, "S": 2, "h1": 5, "h2": 7}]


@pytest.mark.parametrize("activation", ACTIVATIONS)
@pytest.mark.parametrize("shape", SHAPES, ids=["stack-box", "subsets", "index-order", "one-model", "no-box", "widths"])
def test_compiled_loops_are_the_torch_loops(activation: str, shape: dict) -> None:
    tensors, kw = _problem(K=5, **shape)
    with torch.no_grad():
        tensors[0].mul_(1.2)  # some states pressed against the box (where there is one)
        tensors[2].mul_(3.0)
    g = torch.Generator().manual_seed(3)
    weight = torch.rand(6, *tensors[0].shape, dtype=tensors[0].dtype, generator=g)
    want_traj, want = _solve(activation, tensors, kw, compiled=False, weight=weight)
    got_traj, got = _solve(activation, tensors, kw, compiled=True, weight=weight)
    if kw["box"] is not None:
        lo, hi = kw["box"]
        assert bool(((want_traj == lo) | (want_traj == hi)).any())  # the box held somewhere
    torch.testing.assert_close(got_traj, want_traj, rtol=1e-12, atol=1e-13)
    assert len(got) == 10
    for i, (a, b) in enumerate(zip(got, want)):
        assert float(b.abs().max()) > 0, i
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11, msg=f"input {i}")


def test_one_activation_per_model_in_the_compiled_loops() -> None:
    """Each model's rows with its own activation: the torch loops' numbers (tested against autograd)."""
    mixed = ("relu", "gelu", "tanh")
    tensors, kw = _problem(K=5, M=3, S=2)
    want_traj, want = _solve(mixed, tensors, kw, compiled=False)
    got_traj, got = _solve(mixed, tensors, kw, compiled=True)
    torch.testing.assert_close(got_traj, want_traj, rtol=1e-12, atol=1e-13)
    for a, b in zip(got, want):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("activation", ACTIVATIONS)
def test_float32_loops_are_the_torch_loops(activation: str) -> None:
    tensors, kw = _problem(K=4)
    tensors = [t.detach().float().requires_grad_() for t in tensors]
    kw["box"] = tuple(b.float() for b in kw["box"])
    want_traj, want = _solve(activation, tensors, kw, compiled=False)
    got_traj, got = _solve(activation, tensors, kw, compiled=True)
    assert got_traj.dtype == torch.float32
    torch.testing.assert_close(got_traj, want_traj, rtol=1e-5, atol=1e-5)
    for a, b in zip(got, want):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("activation", ["tanh", "gelu"])
def test_threaded_loops_are_the_serial_loops(activation: str) -> None:
    """Rows shared among threads do the same arithmetic in the same order: equal to the last bit."""
    tensors, kw = _problem(M=2, S=5, K=6)
    one_traj, one = _solve(activation, tensors, kw, compiled=True, threads=1)
    two_traj, two = _solve(activation, tensors, kw, compiled=True, threads=2)
    assert torch.equal(one_traj, two_traj)
    for a, b in zip(one, two):
        assert torch.equal(a, b)


def test_buffers_are_reused_only_once_free() -> None:
    """Two solves alive at once, a graph kept for a second backward pass, then a solve of the same
    shape after both were freed: every gradient is what a solve alone gives, and freed buffers are
    taken again (not allocated anew)."""
    a_tensors, kw = _problem(K=5)
    b_tensors, _ = _problem(K=5)
    with torch.no_grad():
        b_tensors[2].mul_(-2.0)
    want_a = _solve("tanh", a_tensors, kw, compiled=False)[1]
    want_b = _solve("tanh", b_tensors, kw, compiled=False)[1]
    f = _call("tanh", kw)
    for t in (*a_tensors, *b_tensors):
        t.grad = None
    compiled_solve.SPARE.held.clear()
    ta, tb = f(*a_tensors), f(*b_tensors)  # both alive: b may not take a's buffers
    held = [id(t) for t in compiled_solve.SPARE.held]
    assert len(set(held)) == len(held) == 10  # five kinds each, none shared
    ta.pow(2).sum().backward(retain_graph=True)
    first = [t.grad.clone() for t in a_tensors]
    for t in a_tensors:
        t.grad = None
    tc = f(*b_tensors)  # a's graph is kept: its buffers stay its own
    ta.pow(2).sum().backward()
    tb.pow(2).sum().backward()
    for got, want in ((first, want_a), ([t.grad for t in a_tensors], want_a), ([t.grad for t in b_tensors], want_b)):
        for x, y in zip(got, want):
            torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-11)
    del ta, tb, tc
    before = [id(t) for t in compiled_solve.SPARE.held]
    f(*a_tensors).pow(2).sum().backward()
    assert [id(t) for t in compiled_solve.SPARE.held] == before  # all freed: taken again, none added


def test_buffers_of_an_earlier_shape_are_freed_once_unused() -> None:
    """A solve of other shapes (a stack that lost models, a longer plan) frees the unused buffers
    of the earlier ones: what is held is what the latest solve needed, each buffer once."""
    compiled_solve.SPARE.held.clear()
    a_tensors, kw = _problem(K=5)  # 4·5 = 20 stages
    _call("tanh", kw)(*a_tensors).pow(2).sum().backward()
    kinds = len(compiled_solve.SPARE.held)
    assert kinds >= 5 and all(20 in t.shape for t in compiled_solve.SPARE.held)
    b_tensors, kw = _problem(K=7)  # 28 stages
    for _ in range(2):  # the second solve takes the first one's buffers again
        _call("tanh", kw)(*b_tensors).pow(2).sum().backward()
        held = compiled_solve.SPARE.held
        assert len(held) == kinds and all(28 in t.shape and 20 not in t.shape for t in held)


def test_threaded_whole_trajectory_steps_are_the_serial_steps() -> None:
    """The whole-trajectory loop (:mod:`physmend.ude.rk4_steps`) with its rows shared among threads:
    each row's numbers to the last bit, for as many rows as threads and for more."""
    from physmend.ude.fixed_step import DriveForm, _solve

    g = torch.Generator().manual_seed(3)
    n, w, K = 5, 8, 40
    for R in (2, 5):
        A = (-0.3 * torch.eye(n, dtype=torch.float64) + 0.05 * torch.randn(n, n, dtype=torch.float64, generator=g))[None]
        d = 0.1 * torch.randn(2 * K + 1, R, n, dtype=torch.float64, generator=g)
        pre = 0.1 * torch.randn(2 * K + 1, 1, R, w, dtype=torch.float64, generator=g)
        wu = 0.3 * torch.randn(1, 2, w, dtype=torch.float64, generator=g)
        layers = [(0.3 * torch.randn(1, w, w, dtype=torch.float64, generator=g), torch.zeros(1, 1, w, dtype=torch.float64)),
                  (0.3 * torch.randn(1, w, 2, dtype=torch.float64, generator=g), torch.zeros(1, 1, 2, dtype=torch.float64))]
        form = DriveForm(A, lambda times: (d[:times.shape[0]], pre[:times.shape[0]]), wu, layers,
                         torch.ones(1, 2, dtype=torch.float64), torch.tensor([0, 3]), torch.tensor([1, 4]), "tanh", 1)
        u0 = torch.randn(R, n, dtype=torch.float64, generator=g)
        grid = torch.linspace(0.0, 4.0, K + 1, dtype=torch.float64)[None].expand(R, -1).contiguous()
        before = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            one = _solve(form, u0, grid)
            torch.set_num_threads(2)
            two = _solve(form, u0, grid)
        finally:
            torch.set_num_threads(before)
        assert one is not None and two is not None
        assert float(one[0].abs().max()) > 0
        assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])


def test_the_shared_twin_is_compiled_ahead_only_where_threads_share_rows() -> None:
    """``warm_shared``: in a fresh process, the whole-trajectory loop's threaded twin has no compiled
    signature until it runs; with one thread it stays so, with two it has one (compiled or read back)
    — also from a process on one torch thread told the later solves' two (a sweep's worker for
    discover's mask stage), whose torch thread count is left as it was."""
    import subprocess
    import sys

    code = ("import torch; from physmend.ude import rk4_steps; from physmend.ude.fixed_step import warm_shared;"
            "torch.set_num_threads(1); warm_shared(); a = len(rk4_steps.steps_threads.signatures);"
            "warm_shared(threads=2); print(a, len(rk4_steps.steps_threads.signatures), torch.get_num_threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.split() == ["0", "1", "1"]


@pytest.mark.parametrize("K", [9600, 30, 7])
def test_tall_products_in_chunks_are_one_product(K: int) -> None:
    """With fewer models than threads the weight gradients' sums over stages are taken in chunks:
    the same numbers as one product, to rounding; one thread: one product, the same bits."""
    g = torch.Generator().manual_seed(5)
    a, b = (torch.randn(1, K, w, dtype=torch.float64, generator=g) for w in (6, 4))
    want = torch.bmm(a.transpose(1, 2), b)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert torch.equal(compiled_solve.tall_product(a, b), want)
        torch.set_num_threads(2)
        got = compiled_solve.tall_product(a, b)
    finally:
        torch.set_num_threads(before)
    assert got.shape == want.shape == (1, 6, 4)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * K**0.5)


def test_one_model_on_two_threads_is_the_serial_solve() -> None:
    """One model, two threads (the weight gradients in chunks): the one-thread numbers to rounding."""
    tensors, kw = _problem(M=1, S=4, K=6)
    one_traj, one = _solve("tanh", tensors, kw, compiled=True, threads=1)
    two_traj, two = _solve("tanh", tensors, kw, compiled=True, threads=2)
    assert torch.equal(one_traj, two_traj)
    for a, b in zip(one, two):
        assert float(b.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)
