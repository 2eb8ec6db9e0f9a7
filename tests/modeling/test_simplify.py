"""Structural simplification: exactness against a direct DAE solve, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import sympy as sp
import torch

from physmend.modeling import Model, ModelError, compile_model
from physmend.modeling import thermal as th
from physmend.simulate import odeint


def tank_network() -> Model:
    """Two tanks and a heated room: aliases, a nonlinear algebraic equation, a linear algebraic loop."""
    m = Model("tanks")
    h1 = m.state("tank1.h", start=2.0, unit="m")
    h2 = m.state("tank2.h", start=0.5, unit="m")
    area = m.parameter("tank.area", 1.5, unit="m2")
    k = m.parameter("valve.k", 0.3, unit="m2.5/s")
    q_in = m.input("pump.q", unit="m3/s")
    q12 = m.variable("pipe.q", unit="m3/s")
    q_alias = m.variable("pipe.q_measured", unit="m3/s")
    q_neg = m.variable("tank2.q_out_of_pipe", unit="m3/s")
    dh = m.variable("pipe.dh", unit="m")
    m.equation(area * m.der(h1), q_in - q12, owner="tank1")
    m.equation(area * m.der(h2), -q_neg - 0.05 * h2, owner="tank2")
    m.equation(dh, h1 - h2, owner="pipe")
    m.equation(q12, k * dh * sp.sqrt(dh**2 + 0.01) / sp.sqrt(sp.Abs(dh) + 0.1), owner="pipe")
    m.equation(q_alias, q12, owner="sensor")
    m.equation(q_neg, -q_alias, owner="tank2")
    # a room behind two series conductors: the middle node makes a linear algebraic loop
    room = th.heat_capacitor(m, "room", 5e4, T_start=15.0)
    amb = th.prescribed_temperature(m, "amb", m.input("ambient.T", unit="degC"))
    g1 = th.thermal_conductor(m, "g1", 20.0)
    g2 = th.thermal_conductor(m, "g2", 30.0)
    m.connect(amb.port, g1.a)
    m.connect(g1.b, g2.a)
    m.connect(g2.b, room.port)
    m.output("tank1.h", h1)
    m.output("room.T", room.T)
    return m


def _inputs(t: float) -> tuple[float, float]:
    return 0.2 + 0.1 * np.sin(t / 50.0), 10.0 + 5.0 * np.cos(t / 300.0)


def dae_reference(model: Model, t_eval: np.ndarray) -> np.ndarray:
    """Solve the DAE as written: at every RHS call, solve *all* equations numerically for the unknowns."""
    states = model.of_kind("state")
    alg = model.of_kind("algebraic")
    ders = [model.der(v.symbol) for v in states]
    unknowns = ders + [v.symbol for v in alg]
    eqs = [e.residual for e in model.equations] + [e.residual for e in model.connection_equations()]
    params = {v.symbol: v.value for v in model.of_kind("parameter")}
    eqs = [e.xreplace(params) for e in eqs]
    inputs = [v.symbol for v in model.of_kind("input")]
    args = [v.symbol for v in states] + inputs
    residual = sp.lambdify([args, unknowns], eqs, "numpy")
    guess = np.ones(len(unknowns))

    def rhs(t: float, u: np.ndarray) -> np.ndarray:
        nonlocal guess
        a = list(u) + list(_inputs(t))
        out = scipy.optimize.root(lambda z: residual(a, z), guess, method="lm", options={"xtol": 1e-14, "ftol": 1e-14})
        sol = out.x
        assert np.max(np.abs(residual(a, sol))) < 1e-9, out.message
        guess = sol
        return sol[: len(states)]

    u0 = np.array([float(v.start) for v in states])
    out = scipy.integrate.solve_ivp(rhs, (t_eval[0], t_eval[-1]), u0, t_eval=t_eval, rtol=1e-10, atol=1e-10, method="LSODA")
    assert out.success
    return out.y.T


def test_simplification_matches_direct_dae_solution() -> None:
    model = tank_network()
    sm = model.simplify()
    assert sm.state_names == ["tank1.h", "tank2.h", "room.T"]
    flows = {"pipe.q", "pipe.q_measured", "tank2.q_out_of_pipe"}
    assert len(flows & set(sm.aliases)) == 2  # three names of one flow: two are aliases
    assert sm.owner["tank1.h"] == "tank1" and sm.owner["room.T"] == "room"
    for expr in list(sm.rhs.values()) + list(sm.observed.values()):
        assert {s.name for s in expr.free_symbols} <= set(sm.state_names + sm.input_names + sm.parameter_names)

    t = np.linspace(0.0, 600.0, 61)
    ref = dae_reference(model, t)

    cm = compile_model(sm)
    tt = torch.as_tensor(t)
    p = cm.default_parameters()[None]

    def f(time: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        q, ta = _inputs(float(time))
        x = torch.tensor([[q, ta]], dtype=u.dtype)
        return cm.rhs(u, x, p)

    got = odeint(f, cm.start(p), tt, method="dopri5", rtol=1e-10, atol=1e-10)[:, 0].numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)


def test_observed_equations_are_explicit_and_consistent() -> None:
    sm = tank_network().simplify()
    cm = compile_model(sm)
    u = torch.tensor([[2.0, 0.5, 15.0]], dtype=torch.float64)
    x = torch.tensor([[0.2, 10.0]], dtype=torch.float64)
    obs = dict(zip(cm.observed_names, cm.observed(u, x, cm.default_parameters()[None])[0].tolist()))
    assert obs["pipe.dh"] == pytest.approx(1.5)
    assert obs["pipe.q_measured"] == pytest.approx(obs["pipe.q"])
    assert obs["tank2.q_out_of_pipe"] == pytest.approx(-obs["pipe.q"])
    # series conductors 20 and 30 W/K: 12 W/K overall, 60 W from 10 degC ambient into a 15 degC room
    assert obs["g1.Q_flow"] == pytest.approx(12.0 * (10.0 - 15.0))
    assert obs["g2.Q_flow"] == pytest.approx(obs["g1.Q_flow"])


def test_wrong_equation_count_is_an_error_naming_unused_unknowns() -> None:
    m = Model("bad")
    x = m.state("x", start=0.0)
    m.variable("unused")
    m.equation(m.der(x), -x)
    with pytest.raises(ModelError, match=r"1 equations for 2 unknowns.*unused"):
        m.simplify()


def test_structurally_singular_model_names_equations() -> None:
    m = Model("singular")
    x = m.state("x", start=0.0)
    a = m.variable("a")
    b = m.variable("b")
    m.equation(m.der(x), a + b, owner="c1")
    m.equation(a + 2 * x, 0, owner="c2", label="c2: first")
    m.equation(2 * a, x, owner="c3", label="c3: second")
    with pytest.raises(ModelError, match=r"(?s)structurally singular.*c[23]"):
        m.simplify()


def test_nonlinear_algebraic_loop_is_an_error_naming_its_equations() -> None:
    m = Model("loop")
    x = m.state("x", start=1.0)
    a = m.variable("a")
    b = m.variable("b")
    m.equation(m.der(x), -a, owner="sink")
    m.equation(a, b**3 + x, owner="loop", label="loop: first")
    m.equation(b, sp.sin(a), owner="loop", label="loop: second")
    with pytest.raises(ModelError, match=r"(?s)loop in .* is nonlinear.*loop: first.*loop: second"):
        m.simplify()


def test_declaration_errors_state_the_rule() -> None:
    m = Model("decl")
    x = m.state("x", start=0.0)
    with pytest.raises(ModelError, match="declared twice"):
        m.parameter("x", 1.0)
    with pytest.raises(ModelError, match="dotted identifiers"):
        m.state("1bad", start=0.0)
    with pytest.raises(ModelError, match=r"low <= value <= high.*low=0.0, value=5.0, high=1.0"):
        m.parameter("k", 5.0, uncertain=True, bounds=(0.0, 1.0))
    with pytest.raises(ModelError, match="needs bounds"):
        m.parameter("k2", 1.0, uncertain=True)
    p = m.parameter("p", 1.0)
    with pytest.raises(ModelError, match="der\\(\\) applies to states only, but 'p' is parameter"):
        m.der(p)
    with pytest.raises(ModelError, match=r"undeclared symbol\(s\) \['zz'\]"):
        m.equation(m.der(x), sp.Symbol("zz"))


def test_builder_loading_from_file_and_errors(tmp_path) -> None:  # noqa: ANN001
    from physmend.modeling import load_model

    src = tmp_path / "my_model.py"
    src.write_text(
        "from physmend.modeling import Model\n"
        "def build(gain=1.0):\n"
        "    m = Model('mine')\n"
        "    x = m.state('x', start=1.0)\n"
        "    m.equation(m.der(x), -gain * x)\n"
        "    m.output('x', x)\n"
        "    return m\n"
        "def not_a_model():\n"
        "    return 3\n"
    )
    model = load_model(f"{src}:build", {"gain": 2.0})
    assert model.name == "mine"
    with pytest.raises(ModelError, match="does not exist"):
        load_model(f"{tmp_path / 'missing.py'}:build")
    with pytest.raises(ModelError, match="has no function 'nope'"):
        load_model(f"{src}:nope")
    with pytest.raises(ModelError, match="must return a physmend.modeling.Model, but returned int"):
        load_model(f"{src}:not_a_model")
    with pytest.raises(ModelError, match="rejected model.options"):
        load_model(f"{src}:build", {"wrong": 1})
    with pytest.raises(ModelError, match="must look like"):
        load_model("no_colon_here")
