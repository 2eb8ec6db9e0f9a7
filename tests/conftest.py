"""A second, non-thermal user model (a mass on a spring with a damper), written only through the
public API into a user config folder, with telemetry from a 'truth' that adds a friction the model
lacks. Proves nothing in the pipeline is cargo-box specific."""

from __future__ import annotations

import os
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.integrate

# the suite runs one process per core: each trains on one thread (``threads: auto`` obeys OpenMP's variable)
os.environ.setdefault("OMP_NUM_THREADS", "1")

MODEL_SOURCE = textwrap.dedent(
    '''
    import sympy as sp
    from physmend.modeling import Model

    def build(damping=0.4):
        m = Model("oscillator", description="mass on a spring with a viscous damper")
        x = m.state("cart.x", start=m.parameter("cart.x0", 0.0, unit="m"), unit="m")
        v = m.state("cart.v", start=0.0, unit="m/s")
        mass = m.parameter("cart.mass", 2.0, unit="kg")
        k = m.parameter("spring.k", 8.0, unit="N/m")
        c = m.parameter("damper.c", damping, unit="N.s/m", uncertain=True, bounds=(0.0, 5.0))
        force = m.input("motor.F", unit="N")
        f_spring = m.variable("spring.F", unit="N")
        f_damper = m.variable("damper.F", unit="N")
        f_net = m.variable("cart.F_net", unit="N")
        m.equation(m.der(x), v, owner="cart")
        m.equation(mass * m.der(v), f_net, owner="cart")
        m.equation(f_net, force - f_spring - f_damper, owner="cart")
        m.equation(f_spring, k * x, owner="spring")
        m.equation(f_damper, c * v, owner="damper")
        m.output("cart.x", x, unit="m")
        return m
    '''
)

TRUE_DRAG = 0.9  # N/(m/s)^2: quadratic air drag the model leaves out


def _force(t: np.ndarray, phase: float) -> np.ndarray:
    return 3.0 * np.sin(0.7 * t + phase) + 1.5 * np.sign(np.sin(0.13 * t))


def _truth(x0: float, phase: float, t: np.ndarray) -> np.ndarray:
    forces = _force(t, phase)  # the truth is driven by the recorded samples, as the model will be

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        x, v = y
        f = float(np.interp(tt, t, forces))
        return [v, (f - 8.0 * x - 0.4 * v - TRUE_DRAG * v * abs(v)) / 2.0]

    sol = scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), [x0, 0.0], t_eval=t, rtol=1e-9, atol=1e-9, max_step=0.05)
    assert sol.success
    return sol.y[0]


@pytest.fixture
def user_project(tmp_path: Path) -> Path:
    """A user's folder: model file, telemetry, and a config dir with model/ and data/ groups."""
    rng = np.random.default_rng(7)
    (tmp_path / "oscillator.py").write_text(MODEL_SOURCE)
    data_dir = tmp_path / "recordings"
    data_dir.mkdir()
    experiments = []
    for i, (x0, phase, role) in enumerate([(0.5, 0.0, "train"), (-0.3, 1.0, "train"), (0.2, 2.0, "test")], 1):
        t = np.arange(0.0, 60.0, 0.1)
        x = _truth(x0, phase, t) + rng.normal(0, 0.003, t.size)
        x[200:230] = np.nan  # a sensor gap
        f = _force(t, phase)
        pd.DataFrame({"t_s": t + 1000.0, "position": x, "motor.F": f}).to_csv(data_dir / f"run{i}.csv", index=False)
        experiments.append(
            f"  - id: run{i}\n    file: run{i}.csv\n    role: {role}\n    parameters: {{cart.x0: {x0}}}\n"
        )
    conf = tmp_path / "my_conf"
    (conf / "model").mkdir(parents=True)
    (conf / "data").mkdir()
    (conf / "model" / "oscillator.yaml").write_text(f"builder: {tmp_path / 'oscillator.py'}:build\noptions: {{}}\n")
    (conf / "data" / "oscillator.yaml").write_text(
        "name: oscillator\n"
        f"root: {data_dir}\n"
        "time_column: t_s\n"
        "columns: {cart.x: position}\n"
        "validation_fraction: 0.2\n"
        "experiments:\n" + "".join(experiments)
    )
    return tmp_path


@pytest.fixture
def reset_mlflow() -> Iterator[None]:
    """After the test: no MLflow run left active, the tracking URI back to MLflow's default."""
    yield
    import mlflow

    while mlflow.active_run() is not None:
        mlflow.end_run()
    mlflow.set_tracking_uri(None)


@pytest.fixture(autouse=True)
def close_figures() -> Iterator[None]:
    """After every test: the matplotlib figures it left open (results a test inspects and drops)
    closed, so one test's figures do not pile up in the next one's worker."""
    yield
    import sys

    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
