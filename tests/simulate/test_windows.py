"""Long records in windows side by side: the sequential solution to tolerance where the model
forgets its start, refused (None) where it does not, where the record is irregular or a solve fails."""

from __future__ import annotations

import numpy as np
import torch

from physmend.modeling import Model, compile_model
from physmend.simulate import from_channels, odeint
from physmend.simulate.windows import MAX_WINDOWS, MIN_ROWS, solve_in_windows


def duffing(damping: float) -> Model:
    """A driven Duffing oscillator (nonlinear: the windows' case, not the exact affine one)."""
    m = Model("duffing")
    x, v = m.state("x", start=0.2, unit="m"), m.state("v", start=0.0, unit="m/s")
    d = m.parameter("d", damping, unit="1/s")
    u = m.input("u", unit="m/s2")
    m.equation(m.der(x), v)
    m.equation(m.der(v), u - 25.0 * x - 8.0 * x**3 - d * v)
    m.output("x", x, unit="m")
    return m


def record(rows: int, jitter: float = 0.0):
    rng = np.random.default_rng(0)
    t = np.arange(rows) * 0.05
    if jitter:
        t = t + rng.uniform(0.0, jitter, rows) * 0.05
        t[0] = 0.0
    inputs = from_channels([[(t, np.sin(0.9 * t) + 0.3 * rng.standard_normal(rows))]])
    return torch.as_tensor(t), inputs


def sequential(rhs, inputs, u0, t, rtol):
    return odeint(lambda tt, uu: rhs(uu, inputs(tt)), u0, t, method="rodas4", rtol=rtol, atol=rtol,
                  options={"tstops": inputs.knots[1:-1], "max_steps": 10**6})


def test_a_damped_record_in_windows_equals_the_sequential_solve_to_tolerance() -> None:
    cm = compile_model(duffing(damping=2.0).simplify())
    p = cm.default_parameters()[None]
    rhs = cm.bind(p)
    t, inputs = record(MIN_ROWS * 17)
    u0 = cm.start(p)
    with torch.no_grad():
        windows = solve_in_windows(rhs, inputs, u0, t, method="rodas4", rtol=1e-5, atol=1e-5)
        truth = sequential(rhs, inputs, u0, t, 1e-8)
        seq = sequential(rhs, inputs, u0, t, 1e-5)
    assert windows is not None and windows.shape == truth.shape
    scale = float(truth.abs().max())
    assert float((windows - truth).abs().max()) < 1e-4 * scale
    # no further from the truth than the sequential solve at the same tolerance, give or take
    assert float((windows - truth).abs().max()) < 5 * float((seq - truth).abs().max()) + 1e-6 * scale


def test_refused_without_damping_on_irregular_times_short_records_and_with_gradients() -> None:
    cm = compile_model(duffing(damping=0.0).simplify())  # remembers its start state for ever
    p = cm.default_parameters()[None]
    t, inputs = record(MIN_ROWS * MAX_WINDOWS)
    with torch.no_grad():
        assert solve_in_windows(cm.bind(p), inputs, cm.start(p), t, method="rodas4", rtol=1e-6, atol=1e-6) is None
        damped = compile_model(duffing(damping=2.0).simplify())
        short_t, short_inputs = record(MIN_ROWS * 8)
        assert solve_in_windows(damped.bind(p), short_inputs, damped.start(p), short_t, method="rodas4",
                                rtol=1e-6, atol=1e-6) is None
        jt, jinputs = record(MIN_ROWS * 17, jitter=0.5)
        assert solve_in_windows(damped.bind(p), jinputs, damped.start(p), jt, method="rodas4", rtol=1e-6, atol=1e-6) is None
        assert solve_in_windows(damped.bind(p), inputs, damped.start(p), t, method="dopri5", rtol=1e-6, atol=1e-6) is None
    assert solve_in_windows(damped.bind(p), inputs, damped.start(p), t, method="rodas4", rtol=1e-6, atol=1e-6) is None


def test_a_failing_window_hands_the_record_back() -> None:
    cm = compile_model(duffing(damping=2.0).simplify())
    p = cm.default_parameters()[None]
    rhs = cm.bind(p)
    t, inputs = record(MIN_ROWS * 17)
    calls = {"n": 0}

    def failing(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        calls["n"] += 1
        out = rhs(u, x)
        return out * float("nan") if calls["n"] > 50 else out  # a right-hand side that breaks part-way

    with torch.no_grad():
        assert solve_in_windows(failing, inputs, cm.start(p), t, method="rodas4", rtol=1e-6, atol=1e-6) is None
