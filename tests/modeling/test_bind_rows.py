"""Parameters bound per experiment with a row index (segments of a few experiments share their
matrices): the same derivatives and the same gradients as parameters repeated per row."""

from __future__ import annotations

import pytest
import torch

from physmend.modeling import Model, compile_model
from physmend.modeling.compile import BoundRhs


def _model(nonlinear: bool):
    m = Model("rows")
    a = m.state("a.x", start=1.0)
    b = m.state("b.x", start=0.0)
    k = m.parameter("k", 2.0)
    g = m.parameter("g", 0.5)
    q = m.input("q")
    m.equation(m.der(a), -k * a + g * b + k * q)  # A and B both depend on the parameters
    m.equation(m.der(b), g * a - b * b if nonlinear else g * a - 3.0 * b + g * q)
    m.output("a.x", a)
    return compile_model(m.simplify())


@pytest.mark.parametrize("nonlinear", [False, True], ids=["affine", "a nonlinear row"])
@pytest.mark.parametrize("experiments", [3, BoundRhs.SHARED_UP_TO + 2], ids=["shared matrices", "many experiments"])
def test_rows_give_the_repeated_parameters_numbers_and_gradients(nonlinear: bool, experiments: int) -> None:
    compiled = _model(nonlinear)
    torch.manual_seed(0)
    p0 = torch.rand(experiments, 2, dtype=torch.float64) + 0.5  # every experiment its own k and g
    rows = torch.randint(0, experiments, (17,))
    rows[:experiments] = torch.arange(experiments)
    u = torch.randn(17, 2, dtype=torch.float64)
    x = torch.randn(17, 1, dtype=torch.float64)
    copies = torch.randn(3, 17, 2, dtype=torch.float64)  # leading dimensions (a Jacobian's copies)
    results = []
    for shared in (True, False):
        p = p0.clone().requires_grad_(True)
        f = compiled.bind(p, rows) if shared else compiled.bind(p[rows])
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
