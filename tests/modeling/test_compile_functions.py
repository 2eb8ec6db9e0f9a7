"""Every elementary sympy function a model may hold compiles to torch (rewritten where the torch
printer lacks it), with the values of sympy's own evaluation and of numpy's, and finite gradients
where the function is smooth."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import sympy as sp
import torch

from physmend.modeling import Model, compile_model
from physmend.modeling.evaluate import evaluate
from physmend.modeling.rewrite import REWRITES, for_torch
from physmend.modeling.safe_parse import parse_safe

U = [-2.3, -0.7, 0.4, 1.3, 2.6]  # away from 0 and from whole numbers: no kink of sign, floor, |u| …
X = [1.7, -0.6, 0.9, -1.4, 0.55]
Builder = Callable[[sp.Symbol, sp.Symbol], sp.Expr]

# name -> (term in the state u and the input x, values of u where it is defined and smooth)
CASES: dict[str, tuple[Builder, list[float]]] = {
    "sin": (lambda u, x: sp.sin(u), U),
    "cos": (lambda u, x: sp.cos(u), U),
    "tan": (lambda u, x: sp.tan(u), [-1.2, -0.7, 0.4, 1.1, 1.3]),
    "cot": (lambda u, x: sp.cot(u), U),
    "sec": (lambda u, x: sp.sec(u), U),
    "csc": (lambda u, x: sp.csc(u), U),
    "asin": (lambda u, x: sp.asin(u), [-0.9, -0.3, 0.1, 0.5, 0.95]),
    "acos": (lambda u, x: sp.acos(u), [-0.9, -0.3, 0.1, 0.5, 0.95]),
    "atan": (lambda u, x: sp.atan(u), U),
    "acot": (lambda u, x: sp.acot(u), U),
    "asec": (lambda u, x: sp.asec(u), [-3.0, -1.5, 1.2, 2.0, 4.0]),
    "acsc": (lambda u, x: sp.acsc(u), [-3.0, -1.5, 1.2, 2.0, 4.0]),
    "sinh": (lambda u, x: sp.sinh(u), U),
    "cosh": (lambda u, x: sp.cosh(u), U),
    "tanh": (lambda u, x: sp.tanh(u), U),
    "coth": (lambda u, x: sp.coth(u), U),
    "sech": (lambda u, x: sp.sech(u), U),
    "csch": (lambda u, x: sp.csch(u), U),
    "asinh": (lambda u, x: sp.asinh(u), U),
    "acosh": (lambda u, x: sp.acosh(u), [1.1, 1.5, 2.0, 3.3, 7.0]),
    "atanh": (lambda u, x: sp.atanh(u), [-0.9, -0.3, 0.1, 0.5, 0.95]),
    "acoth": (lambda u, x: sp.acoth(u), [-3.0, -1.5, 1.2, 2.0, 4.0]),
    "asech": (lambda u, x: sp.asech(u), [0.1, 0.3, 0.5, 0.8, 0.95]),
    "acsch": (lambda u, x: sp.acsch(u), U),
    "exp": (lambda u, x: sp.exp(u), U),
    "log": (lambda u, x: sp.log(sp.Abs(u)), U),
    "log_base": (lambda u, x: sp.log(sp.Abs(u), 10), U),
    "sqrt": (lambda u, x: sp.sqrt(sp.Abs(u)), U),
    "power_fitted": (lambda u, x: sp.Abs(u) ** sp.Float(1.37), U),
    "power_rational": (lambda u, x: sp.Abs(u) ** sp.Rational(2, 3) + u**3, U),
    "Abs": (lambda u, x: sp.Abs(u) * x, U),
    "sign": (lambda u, x: sp.sign(u) * x, U),
    "Heaviside": (lambda u, x: sp.Heaviside(u) * x, U),
    "floor": (lambda u, x: sp.floor(u) + u, U),
    "ceiling": (lambda u, x: sp.ceiling(u) * u, U),
    "frac": (lambda u, x: sp.frac(u), U),
    "erf": (lambda u, x: sp.erf(u), U),
    "erfc": (lambda u, x: sp.erfc(u), U),
    "sinc": (lambda u, x: sp.sinc(u), U),
    "atan2": (lambda u, x: sp.atan2(u, x), U),  # every quadrant: u and x take both signs
    "Min": (lambda u, x: sp.Min(u, x), U),
    "Max": (lambda u, x: sp.Max(u, x, 0.5), U),
    "Piecewise": (lambda u, x: sp.Piecewise((u**2, u > x), (sp.sin(u), sp.And(u <= x, x > 1)), (-x, True)), U),
    "Piecewise_numbers": (lambda u, x: sp.Piecewise((2.5, u > 0), (-1, sp.Or(x < 0, u < -2)), (0.1, True)), U),
    "Piecewise_eq_ne": (lambda u, x: sp.Piecewise((x, sp.Ne(u, 0.4)), (u, True)), U),
    "functions_of_numbers": (lambda u, x: sp.cot(2) * u + sp.log(3) * x + sp.sech(1), U),
}

#: points (indices) where a case is evaluated on purpose at its switch, where it has no derivative
KINKS = {"Piecewise_eq_ne": (2,)}


def _build(case: str) -> tuple[Model, sp.Expr]:
    """``w = f(u, x)`` (an algebraic variable, solved by the simplification), ``du/dt = k·w − 0.1·u``."""
    m = Model(f"fn_{case}")
    u = m.state("u", start=0.5)
    x = m.input("x")
    k = m.parameter("k", 1.3)
    term = CASES[case][0](u, x)
    w = m.variable("w")
    m.equation(w, term, owner="f")
    m.equation(m.der(u), k * w - 0.1 * u, owner="u")
    m.output("w", w)
    return m, term


def _numpy(expr: sp.Expr, u: np.ndarray, x: np.ndarray) -> np.ndarray:
    f = sp.lambdify([sp.Symbol("u", real=True), sp.Symbol("x", real=True)], expr, modules=["scipy", "numpy"])
    return np.broadcast_to(np.asarray(f(u, x), dtype=float), u.shape)


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_function_compiles_with_the_values_of_sympy_and_numpy(case: str) -> None:
    model, term = _build(case)
    simple = model.simplify()
    compiled = compile_model(simple)
    us = np.array(CASES[case][1])
    xs = np.array(X)
    u_t = torch.tensor(us, dtype=torch.float64).unsqueeze(-1).requires_grad_(True)
    x_t = torch.tensor(xs, dtype=torch.float64).unsqueeze(-1)
    p_t = compiled.default_parameters().expand(len(us), -1)
    du = compiled.rhs(u_t, x_t, p_t)
    w = compiled.outputs(u_t, x_t, p_t)[:, 0]
    assert du.dtype == torch.float64 and w.dtype == torch.float64

    u_s, x_s = sp.Symbol("u", real=True), sp.Symbol("x", real=True)
    exact = np.array([float(term.subs({u_s: a, x_s: b}).evalf(30)) for a, b in zip(us, xs)])  # sympy's own value
    np.testing.assert_allclose(w.detach().numpy(), exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(_numpy(term, us, xs), exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(evaluate(term, {"u": us, "x": xs}) if not term.has(sp.erf, sp.erfc) else exact,
                               exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(du[:, 0].detach().numpy(), 1.3 * exact - 0.1 * us, rtol=1e-10, atol=1e-12)

    # gradients: finite, and the derivative of the function (central differences) where it is smooth
    grad = torch.autograd.grad(w.sum(), u_t)[0] if w.requires_grad else torch.zeros_like(u_t)  # a step: none
    h = 1e-6
    slope = (_numpy(term, us + h, xs) - _numpy(term, us - h, xs)) / (2 * h)
    assert torch.isfinite(grad).all(), grad
    smooth = [i for i in range(len(us)) if i not in KINKS.get(case, ())]
    np.testing.assert_allclose(grad[smooth, 0].numpy(), slope[smooth], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fn", [sp.cot, sp.sech, sp.acsc, sp.coth, sp.asec, sp.Heaviside])
def test_a_function_of_parameters_only_goes_into_the_affine_coefficients(fn: type) -> None:
    m = Model("affine")
    v = m.state("v", start=1.0)
    x = m.input("x")
    k = m.parameter("k", 1.3)
    m.equation(m.der(v), -fn(k) * v + fn(k + 1) * x, owner="v")
    m.output("v", v)
    compiled = compile_model(m.simplify())
    assert compiled.affine
    p = torch.tensor([[1.3], [2.2]], dtype=torch.float64)
    v_t = torch.tensor([[0.5], [-1.0]], dtype=torch.float64)
    x_t = torch.tensor([[2.0], [3.0]], dtype=torch.float64)
    want = [float((-fn(a) * b + fn(a + 1) * c).evalf(30)) for a, b, c in ((1.3, 0.5, 2.0), (2.2, -1.0, 3.0))]
    for du in (compiled.rhs(v_t, x_t, p), compiled.bind(p)(v_t, x_t)):
        np.testing.assert_allclose(du[:, 0].numpy(), want, rtol=1e-10)


def test_float32_models_stay_float32_with_piecewise_numbers() -> None:
    model, _ = _build("Piecewise_numbers")
    compiled = compile_model(model.simplify())
    u = torch.tensor([[0.3], [-0.4]], dtype=torch.float32)
    out = compiled.outputs(u, torch.ones_like(u), compiled.default_parameters(torch.float32).expand(2, -1))
    assert out.dtype == torch.float32 and out[:, 0].tolist() == [2.5, pytest.approx(0.1)]


def test_the_rewrite_leaves_other_expressions_as_they_are() -> None:
    a, b = sp.symbols("a b")
    expr = sp.sin(a) * sp.sqrt(sp.Abs(b)) + sp.Max(a, 0)
    assert for_torch(expr) is expr
    assert all(not for_torch(f(a)).has(f) for f in REWRITES)


@pytest.mark.parametrize("case", sorted(c for c in CASES if not c.startswith("Piecewise")))
def test_a_stored_formula_with_each_function_is_read_back_by_the_restricted_parser(case: str) -> None:
    u, x = sp.Symbol("u"), sp.Symbol("x")
    term = CASES[case][0](u, x)
    back = parse_safe(str(term), {"u": u, "x": x}, where=case)
    assert sp.simplify(back - term) == 0 or back == term, (term, back)
    assert parse_safe("abs(0.5*u) ^ 1.37", {"u": u}) == sp.Abs(0.5 * u) ** sp.Float(1.37)  # pyoperon's powabs
    assert parse_safe("powabs(u, 1.37)", {"u": u}) == sp.Abs(u) ** sp.Float(1.37)


def test_a_rows_affine_terms_stay_in_the_matrices_and_only_its_other_terms_are_evaluated_apart() -> None:
    m = Model("mixed")
    a = m.state("a", start=1.0)
    b = m.state("b", start=0.5)
    c = m.state("c", start=0.1)  # in no nonlinear term: the remainder does not take it
    x = m.input("x")
    k, q = m.parameter("k", 0.7), m.parameter("q", 2.0)
    m.equation(m.der(a), -k * a + 3.0 * x + q * a * b - sp.sqrt(sp.Abs(b)) / q + 1.5, owner="a")
    m.equation(m.der(b), -q * b + c, owner="b")
    m.equation(m.der(c), -c + x, owner="c")
    m.output("a", a)
    compiled = compile_model(m.simplify())
    split = compiled._affine
    assert split is not None and split.nonlinear == [0] and not compiled.affine
    assert split.rest_args == ([0, 1], [], [1])  # a, b and q: not c, x, k
    p = torch.tensor([[0.7, 2.0], [1.1, 0.5]], dtype=torch.float64)
    bound = compiled.bind(p)
    # the affine part of the nonlinear row is in A, B and c: -k on a, 3 on x, 1.5
    assert bound.A[:, 0].tolist() == [[-0.7, 0.0, 0.0], [-1.1, 0.0, 0.0]]
    assert bound.B[:, 0, 0].tolist() == [3.0, 3.0] and bound.c[:, 0].tolist() == [1.5, 1.5]
    u = torch.tensor([[0.3, -1.2, 0.4], [1.5, 0.8, -0.2]], dtype=torch.float64)
    xs = torch.tensor([[0.9], [-0.4]], dtype=torch.float64)
    for uu, xx in ((u, xs), (u.expand(4, -1, -1), xs.expand(4, -1, -1))):  # a step, and a whole trajectory
        np.testing.assert_allclose(bound(uu, xx).numpy(), compiled.rhs(uu, xx, p.expand(*uu.shape[:-1], -1)).numpy(),
                                   rtol=1e-14, atol=1e-14)
    want = [-k0 * a0 + 3.0 * x0 + q0 * a0 * b0 - abs(b0) ** 0.5 / q0 + 1.5
            for (k0, q0), (a0, b0, _), (x0,) in zip(p.tolist(), u.tolist(), xs.tolist())]
    np.testing.assert_allclose(bound(u, xs)[:, 0].numpy(), want, rtol=1e-14)
    # gradients reach the parameters through both parts
    pg = p.clone().requires_grad_(True)
    compiled.bind(pg)(u, xs)[:, 0].sum().backward()
    want_dk = [-a0 for a0, _, _ in u.tolist()]
    want_dq = [a0 * b0 + abs(b0) ** 0.5 / q0**2 for (_, q0), (a0, b0, _) in zip(p.tolist(), u.tolist())]
    np.testing.assert_allclose(pg.grad.numpy(), np.array([want_dk, want_dq]).T, rtol=1e-12)


def test_a_bound_nonlinear_physics_serves_several_backward_passes() -> None:
    m = Model("twice")
    a = m.state("a", start=1.0)
    q = m.parameter("q", 2.0)
    m.equation(m.der(a), -a + q * a * a, owner="a")
    m.output("a", a)
    compiled = compile_model(m.simplify())
    p = torch.tensor([[2.0]], dtype=torch.float64, requires_grad=True)
    bound = compiled.bind(p)
    for value in (0.5, -1.5):  # one bound physics, two losses, two backward passes
        bound(torch.tensor([[value]], dtype=torch.float64), torch.zeros(1, 0, dtype=torch.float64)).sum().backward()
    assert p.grad is not None and float(p.grad) == pytest.approx(0.5**2 + 1.5**2)
