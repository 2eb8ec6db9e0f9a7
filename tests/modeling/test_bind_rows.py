"""Parameters bound per experiment with a row index (segments of a few experiments share their
matrices): the same derivatives and the same gradients as parameters repeated per row."""

from __future__ import annotations

import pytest
import torch

from physmend.modeling import Model, compile_model
from physmend.modeling.compile import BoundRhs


N = BoundRhs.SHARED_MIN_STATES  # a chain of as many states as the shared product needs


def _model(nonlinear: bool):
    m = Model("rows")
    xs = [m.state(f"n{i}.x", start=float(i)) for i in range(N)]
    k = m.parameter("k", 2.0)
    g = m.parameter("g", 0.5)
    q = m.input("q")
    m.equation(m.der(xs[0]), -k * xs[0] + g * xs[1] + k * q)  # A and B both depend on the parameters
    for i in range(1, N - 1):
        m.equation(m.der(xs[i]), g * xs[i - 1] - k * xs[i] + 0.1 * xs[i + 1])
    last = g * xs[-2] - xs[-1] * xs[-1] if nonlinear else g * xs[-2] - 3.0 * xs[-1] + g * q
    m.equation(m.der(xs[-1]), last)
    m.output("n0.x", xs[0])
    return compile_model(m.simplify())


@pytest.mark.parametrize("nonlinear", [False, True], ids=["affine", "a nonlinear row"])
@pytest.mark.parametrize("experiments", [3, BoundRhs.SHARED_MAX_COLUMNS // N + 1], ids=["shared matrices", "many experiments"])
def test_rows_give_the_repeated_parameters_numbers_and_gradients(nonlinear: bool, experiments: int) -> None:
    compiled = _model(nonlinear)
    torch.manual_seed(0)
    p0 = torch.rand(experiments, 2, dtype=torch.float64) + 0.5  # every experiment its own k and g
    rows = torch.randint(0, experiments, (17,))
    rows[:experiments] = torch.arange(experiments)
    u = torch.randn(17, N, dtype=torch.float64)
    x = torch.randn(17, 1, dtype=torch.float64)
    copies = torch.randn(3, 17, N, dtype=torch.float64)  # leading dimensions (a Jacobian's copies)
    results = []
    for shared in (True, False):
        p = p0.clone().requires_grad_(True)
        f = compiled.bind(p, rows) if shared else compiled.bind(p[rows])
        assert (getattr(f, "_shared", None) is not None) == (shared and experiments * N <= BoundRhs.SHARED_MAX_COLUMNS)
        du, dc = f(u, x), f(copies, x)
        (du.square().sum() + dc.sum()).backward()
        lin = f.linear(u) if isinstance(f, BoundRhs) else None
        results.append((du.detach(), dc.detach(), p.grad.clone(), lin))
    (du_s, dc_s, g_s, lin_s), (du_r, dc_r, g_r, lin_r) = results
    assert float(du_r.std(0).abs().min()) > 0 and float(g_r.abs().min()) > 0
    torch.testing.assert_close(du_s, du_r, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(dc_s, dc_r, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_s, g_r, rtol=1e-10, atol=1e-12)
    if lin_s is not None:
        torch.testing.assert_close(lin_s, lin_r, rtol=1e-12, atol=1e-12)
