"""Batched simulation: closed-form accuracy, stiffness, batched == one-by-one, clear failures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physmend.modeling import Model, compile_model
from physmend.modeling import thermal as th
from physmend.simulate import PiecewiseLinear, SimulationError, available_methods, from_channels, odeint


def rc_model() -> Model:
    """A room (C) behind a conductance (G) to an ambient input, with a heater input."""
    m = Model("rc")
    C = m.parameter("room.C", 2.0e5, unit="J/K")
    G = m.parameter("wall.G", 50.0, unit="W/K")
    room = th.heat_capacitor(m, "room", C, T_start=m.parameter("room.T0", 5.0, unit="K"))
    amb = th.prescribed_temperature(m, "amb", m.input("ambient.T"))
    heat = th.prescribed_heat_flow(m, "heater", m.input("heater.Q"))
    wall = th.thermal_conductor(m, "wall", G)
    m.connect(amb.port, wall.a)
    m.connect(wall.b, room.port, heat.port)
    m.output("room.T", room.T)
    return m


@pytest.mark.parametrize("method", ["rosenbrock23", "dopri5"])
def test_matches_closed_form_first_order_response(method: str) -> None:
    cm = compile_model(rc_model().simplify())
    # three experiments with different conductances, ambient and heater steps held constant
    p = cm.default_parameters().repeat(3, 1)
    p[:, cm.parameter_names.index("wall.G")] = torch.tensor([20.0, 50.0, 400.0], dtype=torch.float64)
    x = torch.tensor([[20.0, 0.0], [-5.0, 300.0], [30.0, 1000.0]], dtype=torch.float64)
    t = torch.linspace(0.0, 20000.0, 201, dtype=torch.float64)
    u = odeint(lambda tt, uu: cm.rhs(uu, x, p), cm.start(p), t, method=method, rtol=1e-8, atol=1e-8)
    G = p[:, 1]
    C, T0 = 2.0e5, 5.0
    T_inf = x[:, 0] + x[:, 1] / G
    exact = T_inf + (T0 - T_inf) * torch.exp(-t[:, None] * G / C)
    torch.testing.assert_close(u[..., 0], exact, rtol=1e-5, atol=1e-5)


def test_batched_equals_one_by_one() -> None:
    cm = compile_model(rc_model().simplify())
    t_knots = [np.array([0.0, 300.0, 900.0, 4000.0]), np.array([0.0, 60.0, 4000.0]), np.array([0.0, 4000.0])]
    chans = [
        [(t_knots[b], 10.0 + 5 * np.sin(t_knots[b] / 500 + b)), (t_knots[b], 200.0 * b + 50 * np.cos(t_knots[b] / 300))]
        for b in range(3)
    ]
    p = cm.default_parameters().repeat(3, 1)
    p[:, 0] = torch.tensor([1e5, 2e5, 4e5], dtype=torch.float64)
    t = torch.linspace(0.0, 4000.0, 81, dtype=torch.float64)
    batched_inputs = from_channels(chans)
    u_all = odeint(lambda tt, uu: cm.rhs(uu, batched_inputs(tt), p), cm.start(p), t, rtol=1e-9, atol=1e-9)
    for b in range(3):
        inp = from_channels([chans[b]])
        u_one = odeint(lambda tt, uu: cm.rhs(uu, inp(tt), p[b : b + 1]), cm.start(p[b : b + 1]), t, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(u_all[:, b], u_one[:, 0], rtol=1e-6, atol=1e-6)


def test_stiff_problem_takes_few_rosenbrock_steps() -> None:
    """A time constant of 1 ms over a 1000 s horizon: the L-stable solver steps by accuracy."""
    calls = {"n": 0}
    k, w = 1000.0, 0.01

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        return -k * (u - torch.cos(w * t))

    t = torch.linspace(0.0, 1000.0, 101, dtype=torch.float64)
    u = odeint(f, torch.zeros(1, 1, dtype=torch.float64), t, rtol=1e-5, atol=1e-6)
    a, b = k * k / (k * k + w * w), k * w / (k * k + w * w)
    periodic = a * torch.cos(w * t) + b * torch.sin(w * t)
    exact = periodic - a * torch.exp(-k * t)  # starts at 0
    assert float((u[:, 0, 0] - exact).abs().max()) < 1e-4
    # an explicit solver is stability-bound to steps below ~2.8 ms: ~ 360 000 steps here
    assert calls["n"] < 10_000


def test_failure_names_experiment_and_time() -> None:
    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:  # blows up at t = 1/u0 for u0 > 0
        return u**2

    u0 = torch.tensor([[-1.0], [0.5]], dtype=torch.float64)
    t = torch.linspace(0.0, 5.0, 6, dtype=torch.float64)
    for method in ("rosenbrock23", "dopri5"):
        with pytest.raises(SimulationError, match=r"(?s)'warm'.*at t = (1\.9|2)"):
            odeint(f, u0, t, method=method, names=["cold", "warm"])


def test_unknown_method_lists_valid_names() -> None:
    with pytest.raises(SimulationError, match=r"simulate.method must be one of \[.*'dopri5'.*'rosenbrock23'.*\], but got 'rk5'"):
        odeint(lambda t, u: -u, torch.ones(1, 1, dtype=torch.float64), torch.tensor([0.0, 1.0], dtype=torch.float64), method="rk5")
    assert "rosenbrock23" in available_methods()


def test_piecewise_linear_holds_ends_and_interpolates() -> None:
    pl = PiecewiseLinear(torch.tensor([0.0, 10.0, 20.0], dtype=torch.float64), torch.tensor([[[0.0], [10.0], [0.0]]], dtype=torch.float64))
    assert float(pl(5.0)) == pytest.approx(5.0)
    assert float(pl(15.0)) == pytest.approx(5.0)
    assert float(pl(-3.0)) == pytest.approx(0.0) and float(pl(30.0)) == pytest.approx(0.0)
    many = pl.at(torch.tensor([2.5, 12.5], dtype=torch.float64))
    assert many.shape == (2, 1, 1) and many[:, 0, 0].tolist() == pytest.approx([2.5, 7.5])
    assert math.isclose(float(pl(10.0)), 10.0)


def test_bound_rhs_equals_generic_rhs_with_gradients() -> None:
    """The affine fast path (``bind``: constant coefficients precomputed once, the others from the
    parameters) gives the generic lambdified derivatives, and the same parameter gradients."""
    cm = compile_model(rc_model().simplify())
    assert cm._affine is not None and cm._affine.varying and len(cm._affine.varying) < len(cm._affine.constant)
    gen = torch.Generator().manual_seed(3)
    p = (cm.default_parameters() * (1 + 0.3 * torch.rand(4, len(cm.parameter_names), generator=gen, dtype=torch.float64)))
    u = torch.randn(5, 4, len(cm.state_names), generator=gen, dtype=torch.float64) * 10
    x = torch.randn(5, 4, len(cm.input_names), generator=gen, dtype=torch.float64) * 100
    p_fast = p.clone().requires_grad_(True)
    p_slow = p.clone().requires_grad_(True)
    fast = cm.bind(p_fast)(u, x)
    slow = cm.rhs(u, x, p_slow)
    torch.testing.assert_close(fast, slow, rtol=1e-12, atol=1e-12)
    fast.pow(2).sum().backward()
    slow.pow(2).sum().backward()
    assert p_slow.grad is not None and bool(p_slow.grad.abs().sum() > 0)
    torch.testing.assert_close(p_fast.grad, p_slow.grad, rtol=1e-10, atol=1e-14)


def test_evaluation_times_must_not_decrease_and_the_error_names_them() -> None:
    import torch

    from physmend.simulate.rodas import odeint_rodas
    from physmend.simulate.rosenbrock import odeint_rosenbrock

    t = torch.tensor([0.0, 10.0, 5.0], dtype=torch.float64)
    u0 = torch.zeros(1, 1, dtype=torch.float64)
    for solve in (odeint_rodas, odeint_rosenbrock):
        with pytest.raises(SimulationError, match=r"non-decreasing, but t\[2\] = 5 s follows t\[1\] = 10 s"):
            solve(lambda tt, u: -u, u0, t)
