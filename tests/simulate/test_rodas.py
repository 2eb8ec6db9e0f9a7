"""Rodas3 / Rodas4 / Rodas4P2: order, tolerance, agreement with rosenbrock23, batching, clear failures."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch

from physmend.simulate import SimulationError, available_methods, from_channels, odeint
from physmend.simulate.rodas import odeint_rodas, rodas_step
from physmend.simulate.tableaus import TABLEAUS
from physmend.simulate.rosenbrock import odeint_rosenbrock

F64 = torch.float64
Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def linear_problem(lam: float) -> tuple[torch.Tensor, Rhs, Rhs, Callable[[torch.Tensor], torch.Tensor]]:
    """``u' = A u + g(t)``, eigenvalues -1 and ``lam``, exact solution ``(1 + sin t, cos 2t)``.

    Returns ``A (2, 2)``, ``f``, the exact ``df/dt`` as ``dfdt(t, u)``, and the solution ``(..., 2)``.
    """
    V = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=F64)
    A = V @ torch.diag(torch.tensor([-1.0, lam], dtype=F64)) @ torch.linalg.inv(V)

    def exact(t: torch.Tensor) -> torch.Tensor:
        return torch.stack([1 + torch.sin(t), torch.cos(2 * t)], -1)

    def d_exact(t: torch.Tensor) -> torch.Tensor:
        return torch.stack([torch.cos(t), -2 * torch.sin(2 * t)], -1)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return u @ A.T + d_exact(t) - exact(t) @ A.T

    def dfdt(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        dd = torch.stack([-torch.sin(t), -4 * torch.cos(2 * t)], -1)
        return (dd - d_exact(t) @ A.T).expand_as(u)

    return A, f, dfdt, exact


def fixed_step_error(name: str, lam: float, n_steps: int, horizon: float = 2.0) -> float:
    A, f, dfdt, exact = linear_problem(lam)
    h = horizon / n_steps
    u = exact(torch.tensor(0.0, dtype=F64))[None]
    for i in range(n_steps):
        t = torch.tensor(i * h, dtype=F64)
        u = rodas_step(f, t, u, h, f(t, u), A[None], dfdt(t, u), TABLEAUS[name]).u_new
    return float((u[0] - exact(torch.tensor(horizon, dtype=F64))).abs().max())


@pytest.mark.parametrize("name", ["rodas3", "rodas4", "rodas4p", "rodas4p2"])
def test_fixed_steps_converge_with_the_method_order_in_the_stiff_limit(name: str) -> None:
    errors = [fixed_step_error(name, -1e6, n) for n in (10, 20, 40)]
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert min(orders) > TABLEAUS[name].order - 0.3, (errors, orders)


@pytest.mark.parametrize("name", ["rodas4p", "rodas4p2"])
def test_rodas4p_keeps_order_four_where_rodas4_loses_it(name: str) -> None:
    """Stiff mode -1e4 with steps 0.2 .. 0.025 s (h lam 2000 .. 250): the regime of fast thermal
    nodes following their inputs. Rodas4's error stalls here (order reduction)."""
    errors = [fixed_step_error(name, -1e4, n) for n in (10, 20, 40, 80)]
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(3)]
    assert min(orders) > 3.8, (errors, orders)
    stalled = [fixed_step_error("rodas4", -1e4, n) for n in (40, 80)]
    assert stalled[0] / stalled[1] < 4.0  # worse than first order between these two


def test_dense_output_is_third_order() -> None:
    A, f, dfdt, exact = linear_problem(-1.0)
    errs = []
    for h in (0.4, 0.2, 0.1):
        t = torch.tensor(0.3, dtype=F64)
        u = exact(t)[None]
        step = rodas_step(f, t, u, h, f(t, u), A[None], dfdt(t, u), TABLEAUS["rodas4p2"])
        errs.append(float((step.dense(0.37)[0] - exact(t + 0.37 * h)).abs().max()))
    assert min(math.log2(errs[i] / errs[i + 1]) for i in range(2)) > 3.5  # local error O(h^4)


def prothero_robinson(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    return -1e6 * (u - torch.sin(t)) + torch.cos(t)


@pytest.mark.parametrize("method", ["rodas3", "rodas4", "rodas4p2"])
def test_prothero_robinson_error_within_tolerance(method: str) -> None:
    t = torch.linspace(0.0, 10.0, 3, dtype=F64)
    u0 = torch.tensor([[0.0], [0.5]], dtype=F64)  # the second starts off the smooth solution
    u = odeint(prothero_robinson, u0, t, method=method, rtol=1e-6, atol=1e-6)
    assert float((u[1:, :, 0] - torch.sin(t[1:, None])).abs().max()) < 1e-5


def test_tighter_tolerance_reduces_the_error_much_more_than_tenfold() -> None:
    t = torch.linspace(0.0, 10.0, 3, dtype=F64)
    u0 = torch.zeros(1, 1, dtype=F64)
    errors = []
    for rtol in (1e-4, 1e-6):
        u = odeint(prothero_robinson, u0, t, method="rodas4p2", rtol=rtol, atol=rtol)
        errors.append(float((u[:, 0, 0] - torch.sin(t)).abs().max()))
    assert errors[0] < 1e-4 and errors[1] < 1e-6
    assert errors[0] / errors[1] > 20.0  # order 4, local error ~ h^5: about 100^(4/5) = 40 expected


def thermal_problem() -> tuple[Rhs, torch.Tensor, torch.Tensor, list[list[tuple[np.ndarray, np.ndarray]]], torch.Tensor]:
    """Two thermal nodes per element (a light air node, tau ~ 1 s; a heavy wall), three elements
    with their own piecewise-linear ambient temperature and heater power (different knots).

    Returns ``f`` for the batch, ``u0 (3, 2)``, parameters ``(3, 2)`` (air and wall capacity, J/K),
    the channels and the union of all knots (s).
    """
    rng = np.random.default_rng(0)
    channels = []
    for b in range(3):
        tk = np.sort(np.concatenate([[0.0, 4000.0], rng.uniform(0, 4000, 6 + 2 * b)]))
        channels.append([(tk, 10.0 + 8 * np.sin(tk / 700 + b)), (tk, rng.uniform(0, 400, tk.size))])
    params = torch.tensor([[200.0, 4e5], [400.0, 2e5], [100.0, 8e5]], dtype=F64)
    inputs = from_channels(channels)
    u0 = torch.tensor([[5.0, 5.0], [15.0, 10.0], [0.0, 20.0]], dtype=F64)
    return make_thermal(inputs, params), u0, params, channels, inputs.knots


def make_thermal(inputs: object, params: torch.Tensor) -> Rhs:
    g_aw, g_ao, g_wo = 150.0, 20.0, 30.0

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        x = inputs(t)  # type: ignore[operator]
        air, wall = u[..., 0], u[..., 1]
        amb, q = x[:, 0], x[:, 1]
        d_air = (g_aw * (wall - air) + g_ao * (amb - air) + q) / params[:, 0]
        d_wall = (g_aw * (air - wall) + g_wo * (amb - wall)) / params[:, 1]
        return torch.stack([d_air, d_wall], -1)

    return f


@functools.cache
def thermal_rosenbrock23() -> torch.Tensor:
    """The thermal problem at 41 times (0 .. 4000 s) by rosenbrock23 at tolerances 1e-9."""
    f, u0, _, _, knots = thermal_problem()
    t = torch.linspace(0.0, 4000.0, 41, dtype=F64)
    return odeint_rosenbrock(f, u0, t, rtol=1e-9, atol=1e-9, tstops=knots[(knots > 0) & (knots < 4000)])


@pytest.mark.parametrize("method", ["rodas3", "rodas4", "rodas4p2"])
def test_agrees_with_rosenbrock23_on_a_batched_problem_with_input_kinks(method: str) -> None:
    f, u0, _, _, knots = thermal_problem()
    t = torch.linspace(0.0, 4000.0, 41, dtype=F64)
    stops = knots[(knots > 0) & (knots < 4000)]
    ours = odeint(f, u0, t, method=method, rtol=1e-9, atol=1e-9, options={"tstops": stops})
    torch.testing.assert_close(ours, thermal_rosenbrock23(), rtol=0, atol=1e-5)
    loose = odeint(f, u0, t, method=method, rtol=1e-6, atol=1e-6, options={"tstops": stops})
    torch.testing.assert_close(loose, ours, rtol=0, atol=1e-4)


def test_batch_equals_one_by_one() -> None:
    _, u0, params, channels, _ = thermal_problem()
    t = torch.linspace(0.0, 4000.0, 21, dtype=F64)
    batched = from_channels(channels)
    stops = batched.knots[(batched.knots > 0) & (batched.knots < 4000)]
    u_all = odeint_rodas(make_thermal(batched, params), u0, t, rtol=1e-8, atol=1e-8, tstops=stops)
    for b in range(3):
        alone = from_channels([channels[b]])
        u_one = odeint_rodas(make_thermal(alone, params[b : b + 1]), u0[b : b + 1], t, rtol=1e-8, atol=1e-8,
                             tstops=alone.knots[(alone.knots > 0) & (alone.knots < 4000)])
        torch.testing.assert_close(u_all[:, b], u_one[:, 0], rtol=0, atol=1e-6)


def test_exact_jacobian_gives_the_finite_difference_result() -> None:
    f, u0, params, _, knots = thermal_problem()
    g_aw, g_ao, g_wo = 150.0, 20.0, 30.0
    jac = torch.zeros(3, 2, 2, dtype=F64)
    jac[:, 0, 0] = -(g_aw + g_ao) / params[:, 0]
    jac[:, 0, 1] = g_aw / params[:, 0]
    jac[:, 1, 0] = g_aw / params[:, 1]
    jac[:, 1, 1] = -(g_aw + g_wo) / params[:, 1]
    t = torch.linspace(0.0, 4000.0, 11, dtype=F64)
    stops = knots[(knots > 0) & (knots < 4000)]
    fd = odeint_rodas(f, u0, t, rtol=1e-8, atol=1e-8, tstops=stops)
    exact = odeint_rodas(f, u0, t, rtol=1e-8, atol=1e-8, tstops=stops, jacobian=lambda tt, u: jac)
    torch.testing.assert_close(exact, fd, rtol=0, atol=1e-6)


def test_gradients_flow_through_the_solver() -> None:
    k = torch.tensor(0.7, dtype=F64, requires_grad=True)
    t = torch.tensor([0.0, 1.0, 2.0], dtype=F64)

    def solve(rate: torch.Tensor) -> torch.Tensor:
        return odeint_rodas(lambda tt, u: -rate * u + torch.sin(tt), torch.ones(1, 1, dtype=F64), t,
                            rtol=1e-9, atol=1e-9)[-1, 0, 0]

    (grad,) = torch.autograd.grad(solve(k), k)
    with torch.no_grad():
        fd = (solve(k + 1e-5) - solve(k - 1e-5)) / 2e-5
    assert float(grad) == pytest.approx(float(fd), rel=1e-4)


@pytest.mark.parametrize("method", ["rodas3", "rodas4", "rodas4p2"])
def test_values_at_evaluation_times_are_accurate_where_steps_would_be_long(method: str) -> None:
    """A 1 ms time constant following a slow input: the step-end error estimate is tiny, steps
    would grow to minutes, and the order-3 interpolant between them misses by ~0.1. Steps end on
    the evaluation times instead."""
    k, w = 1000.0, 0.01

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return -k * (u - torch.cos(w * t))

    t = torch.linspace(0.0, 1000.0, 101, dtype=F64)
    u = odeint(f, torch.zeros(1, 1, dtype=F64), t, method=method, rtol=1e-5, atol=1e-6)
    a, b = k * k / (k * k + w * w), k * w / (k * k + w * w)
    exact = a * torch.cos(w * t) + b * torch.sin(w * t) - a * torch.exp(-k * t)
    assert float((u[:, 0, 0] - exact).abs().max()) < 1e-5


@pytest.mark.parametrize("method", ["rodas3", "rodas4", "rodas4p2"])
def test_blow_up_names_experiment_and_time(method: str) -> None:
    """Without the fast-growth check, rodas3 steps over the pole at t = 2 (an L-stable method
    damps a fast growing mode like a decaying one) and continues on the other branch."""

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:  # blows up at t = 1/u0 for u0 > 0
        return u**2

    u0 = torch.tensor([[-1.0], [0.5]], dtype=F64)
    t = torch.linspace(0.0, 5.0, 6, dtype=F64)
    with pytest.raises(SimulationError, match=r"(?s)'warm'.*at t = (1\.9|2)"):
        odeint(f, u0, t, method=method, names=["cold", "warm"])


@pytest.mark.parametrize(
    "t",
    [torch.zeros(2, 2, dtype=F64), torch.zeros(0, dtype=F64), torch.tensor([0.0, 2.0, 1.0], dtype=F64)],
    ids=["2-D", "empty", "decreasing"],
)
def test_bad_times_give_the_errors_of_rosenbrock23(t: torch.Tensor) -> None:
    u0 = torch.ones(1, 1, dtype=F64)
    with pytest.raises(SimulationError) as theirs:
        odeint_rosenbrock(lambda tt, u: -u, u0, t)
    with pytest.raises(SimulationError, match="evaluation times") as ours:
        odeint_rodas(lambda tt, u: -u, u0, t)
    assert str(ours.value) == str(theirs.value)


def test_registered_and_trivial_horizons() -> None:
    assert {"rodas3", "rodas4", "rodas4p2"} <= set(available_methods())
    u0 = torch.ones(2, 1, dtype=F64)
    assert odeint(lambda tt, u: -u, u0, torch.zeros(1, dtype=F64), method="rodas4").shape == (1, 2, 1)
    same = odeint(lambda tt, u: -u, u0, torch.zeros(3, dtype=F64), method="rodas4")
    assert same.shape == (3, 2, 1) and bool((same == 1).all())
    with pytest.raises(SimulationError, match=r"tableau must be one of \['rodas3', 'rodas4', 'rodas4p', 'rodas4p2'\], but got 'x'"):
        odeint_rodas(lambda tt, u: -u, u0, torch.tensor([0.0, 1.0], dtype=F64), tableau="x")
