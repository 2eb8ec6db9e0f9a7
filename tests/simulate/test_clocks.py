"""A clock per batch element: each experiment's steps end on its own times, the results agree with
each experiment solved alone, and the batch takes as many iterations as its busiest element."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physmend.simulate import SimulationError, from_channels, odeint
from physmend.simulate.clocks import odeint_rodas_each

F64 = torch.float64
A = torch.tensor([[-5.0, 1.0], [0.5, -0.5]], dtype=F64)  # time constants about 0.2 s and 2 s
Bm = torch.tensor([[4.0], [0.2]], dtype=F64)


def experiments(n: int = 3, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` records of one input on their own jittered sample times over 20 s (about 4 Hz)."""
    rng = np.random.default_rng(seed)
    out = []
    for b in range(n):
        t = np.sort(np.concatenate([[0.0, 20.0], np.arange(0.25, 20.0, 0.25) + rng.uniform(-0.05, 0.05, 79)]))
        x = np.sin((1.0 + 0.3 * b) * t) + 0.5 * (t > 7 + b)  # a step (steep ramp) and a sine
        out.append((t, x))
    return out


def problem(records: list[tuple[np.ndarray, np.ndarray]]):
    inputs = from_channels([[(t, x)] for t, x in records], F64)
    times = torch.as_tensor(np.unique(np.concatenate([t for t, _ in records])), dtype=F64)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        x = inputs.each(t) if t.ndim == 1 else inputs(t)
        return u @ A.T + x @ Bm.T

    return inputs, times, f


def own_times(records, times: torch.Tensor) -> list[torch.Tensor]:
    return [times[torch.isin(times, torch.as_tensor(t, dtype=F64))] for t, _ in records]


def test_each_element_at_its_own_times_matches_it_solved_alone_and_needs_fewer_iterations() -> None:
    records = experiments()
    inputs, times, f = problem(records)
    u0 = torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.5, -1.0]], dtype=F64)
    stops = [torch.unique(torch.cat([own, k])) for own, k in zip(own_times(records, times), inputs.kinks())]
    calls = {"each": 0, "shared": 0}

    def counted(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        calls["each" if t.ndim == 1 else "shared"] += 1
        return f(t, u)

    got = odeint(counted, u0, times, method="rodas4", rtol=1e-4, atol=1e-4, options={"clocks": stops}, names=["a", "b", "c"])
    odeint(counted, u0, times, method="rodas4", rtol=1e-4, atol=1e-4, options={"tstops": inputs.knots[1:-1]})
    # one shared clock ends steps on all three experiments' times; a clock each on its own only
    assert calls["each"] < 0.6 * calls["shared"], calls
    for b, (t_own, x_own) in enumerate(records):
        alone_in = from_channels([[(t_own, x_own)]], F64)
        t_b = torch.as_tensor(t_own, dtype=F64)

        def f_b(t: torch.Tensor, u: torch.Tensor, alone_in=alone_in) -> torch.Tensor:
            return u @ A.T + alone_in(t) @ Bm.T

        # solved alone with the same tolerances: the same steps, so the same values (to rounding)
        alone = odeint(f_b, u0[b:b + 1], t_b, method="rodas4", rtol=1e-4, atol=1e-4,
                       options={"tstops": t_b[1:-1]})[:, 0]
        rows = torch.searchsorted(times, t_b)
        assert torch.allclose(got[rows, b], alone, atol=1e-7, rtol=0), float((got[rows, b] - alone).abs().max())
        # between its own rows (the other experiments' times) its continuous extension, near the exact solution
        mid = ~torch.isin(times, t_b)
        ref = odeint(f_b, u0[b:b + 1], times, method="rodas4", rtol=1e-10, atol=1e-10,
                     options={"tstops": t_b[1:-1]})[:, 0]
        assert float((got[mid, b] - ref[mid]).abs().max()) < 1e-3  # ten times the tolerance


def test_kinks_are_each_elements_own_knots_only() -> None:
    records = experiments()
    inputs, _, _ = problem(records)
    for (t, _), k in zip(records, inputs.kinks()):
        inner = torch.as_tensor(t[1:-1], dtype=F64)
        assert set(k.tolist()) <= set(inner.tolist())  # never another experiment's knot
        assert k.numel() >= 0.9 * inner.numel()  # and nearly all of its own (a sine bends at each)
    tt = torch.tensor([0.0, 3.3, 25.0], dtype=F64)  # one per element, the last past the end (held)
    assert torch.equal(inputs.each(tt), inputs.at_each(tt[None])[0])


def test_a_diverging_element_is_named_and_the_others_do_not_hide_it() -> None:
    records = experiments()
    inputs, times, _ = problem(records)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        grow = torch.tensor([0.0, 0.0, 1.0], dtype=F64)[:, None] * u.square()  # element c: u' = u², a pole
        return -u + grow

    u0 = torch.tensor([[1.0, 1.0], [1.0, 1.0], [2.0, 2.0]], dtype=F64)  # c's pole at t = ln 2
    stops = [torch.as_tensor(t, dtype=F64) for t, _ in records]
    with pytest.raises(SimulationError, match="'c'"):
        odeint_rodas_each(f, u0, times, stops, rtol=1e-6, atol=1e-6, names=["a", "b", "c"])


def test_a_clock_per_element_needs_one_list_of_stops_per_element() -> None:
    _, times, f = problem(experiments())
    with pytest.raises(SimulationError, match="3 lists of stops, but got 2"):
        odeint_rodas_each(f, torch.zeros(3, 2, dtype=F64), times, [times, times])
