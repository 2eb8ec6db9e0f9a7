"""The exact solution of affine models: equal to a tight Rosenbrock solve, refused where it must be."""

from __future__ import annotations

import numpy as np
import torch

from physmend.modeling import Model, compile_model
from physmend.modeling.compile import BoundRhs
from physmend.simulate import Batch, from_channels, simulate_batch
from physmend.simulate.affine import exact_affine


def two_masses() -> Model:
    """Two coupled masses driven by a force input, one stiff coupling: affine in every row."""
    m = Model("two_masses")
    x1, v1 = m.state("a.x", start=0.1, unit="m"), m.state("a.v", start=0.0, unit="m/s")
    x2 = m.state("b.x", start=-0.2, unit="m")
    k = m.parameter("k", 40.0, unit="N/m")
    d = m.parameter("d", 0.3, unit="N.s/m")
    g = m.parameter("g", 500.0, unit="1/s")  # b follows a fast (stiff against the record's sampling)
    f = m.input("force", unit="N")
    m.equation(m.der(x1), v1)
    m.equation(m.der(v1), f - k * x1 - d * v1 + 2.0)
    m.equation(m.der(x2), g * (x1 - x2))
    m.output("a.x", x1, unit="m")
    m.output("b.x", x2, unit="m")
    return m


def batch_of(cm, ks: list[float]) -> Batch:
    rng = np.random.default_rng(3)
    chans, B = [], len(ks)
    for b in range(B):  # uneven sampling of the input, differently per experiment
        tk = np.sort(np.concatenate([[0.0, 10.0], rng.uniform(0.0, 10.0, 40 + 10 * b)]))
        chans.append([(tk, np.sin(1.3 * tk + b) + 0.2 * rng.standard_normal(tk.size))])
    p = cm.default_parameters().repeat(B, 1)
    p[:, cm.parameter_names.index("k")] = torch.tensor(ks, dtype=torch.float64)
    t = torch.linspace(0.0, 10.0, 301, dtype=torch.float64)
    return Batch(ids=[f"e{b}" for b in range(B)], t=t, obs=torch.full((t.numel(), B, 2), float("nan"), dtype=torch.float64),
                 inputs=from_channels(chans), params=p, u0=cm.start(p), split_time=torch.full((B,), float("inf")))


def test_exact_equals_a_tight_solve_on_uneven_knots_and_per_experiment_parameters() -> None:
    cm = compile_model(two_masses().simplify())
    batch = batch_of(cm, [20.0, 40.0, 90.0])
    with torch.no_grad():
        exact = simulate_batch(cm, batch, method="rodas4", rtol=1e-4, atol=1e-4)
        tight = simulate_batch(cm, batch, method="rodas4", rtol=1e-8, atol=1e-10, options={"max_steps": 10**6}, exact=False)
        loose = simulate_batch(cm, batch, method="rodas4", rtol=1e-4, atol=1e-4, exact=False)
    scale = float(tight.states.abs().max())
    assert float((exact.states - tight.states).abs().max()) < 1e-6 * scale
    # the loose solve (what was used before) is further from the truth than the exact one
    assert float((loose.states - tight.states).abs().max()) > 10 * float((exact.states - tight.states).abs().max())
    torch.testing.assert_close(exact.outputs, tight.outputs, rtol=0, atol=1e-6 * scale)


def test_refused_with_a_gradient_a_nonlinear_row_or_a_blow_up() -> None:
    cm = compile_model(two_masses().simplify())
    batch = batch_of(cm, [40.0])
    p = batch.params.clone().requires_grad_(True)
    assert exact_affine(cm.bind(p), batch.inputs, batch.u0, batch.t) is None  # a gradient is wanted
    with torch.no_grad():
        assert exact_affine(cm.bind(batch.params), batch.inputs, batch.u0, batch.t) is not None
        unstable = batch.params.clone()
        unstable[:, cm.parameter_names.index("k")] = -4.0e4  # grows like exp(200 t): beyond float range by t = 4
        assert exact_affine(cm.bind(unstable), batch.inputs, batch.u0, batch.t) is None
    m2 = Model("cubic")
    x = m2.state("x", start=1.0)
    m2.equation(m2.der(x), -(x**3))
    m2.output("x", x)
    cm2 = compile_model(m2.simplify())
    p2 = cm2.default_parameters().reshape(1, -1)
    bound = cm2.bind(p2)
    assert not isinstance(bound, BoundRhs) or exact_affine(bound, batch.inputs, cm2.start(p2), batch.t) is None
