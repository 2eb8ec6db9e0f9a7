"""Derivative-matching warm start: on a model whose measured state's equation lacks a term, the
regression alone (no ODE solve) recovers that term, leaves the hidden equation alone and already
fits better than the model as written."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.integrate
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude import evaluate, reference
from physmend.ude.hybrid import HybridModel
from physmend.ude.spec import build_spec
from physmend.ude.warmstart import fit_network, forced_trajectories, measured_states

MODEL = textwrap.dedent(
    '''
    from physmend.modeling import Model

    def build():
        m = Model("room", description="room air and a heavy wall")
        air = m.state("air.T", start=20.0, unit="degC")
        wall = m.state("wall.T", start=20.0, unit="degC")
        heater = m.input("heater.P", unit="W")
        outside = m.input("outside.T", unit="degC")
        m.equation(200000.0 * m.der(air), heater + 50.0 * (wall - air), owner="air")
        m.equation(2000000.0 * m.der(wall), 50.0 * (air - wall) + 20.0 * (outside - wall), owner="wall")
        m.output("air.T", air, unit="degC")
        return m
    '''
)


def _leak(air: np.ndarray, outside: np.ndarray) -> np.ndarray:
    """The term the model leaves out: ventilation loss of the air, W."""
    return 15.0 * (outside - air)


@pytest.fixture
def room_project(tmp_path: Path) -> Path:
    rng = np.random.default_rng(3)
    (tmp_path / "room.py").write_text(MODEL)
    conf = tmp_path / "conf"
    (conf / "model").mkdir(parents=True)
    (conf / "data").mkdir()
    (conf / "model" / "room.yaml").write_text(f"builder: {tmp_path / 'room.py'}:build\noptions: {{}}\n")
    lines = []
    for i, phase in enumerate([0.0, 1.3, 2.1], 1):
        t = np.arange(0.0, 6 * 3600.0, 30.0)
        power = 400.0 + 300.0 * np.sign(np.sin(2 * np.pi * t / 5400.0 + phase))
        outside = 5.0 + 3.0 * np.sin(2 * np.pi * t / 20000.0 + phase)

        def rhs(tt: float, y: np.ndarray) -> list[float]:
            a, w = y
            p, o = np.interp(tt, t, power), np.interp(tt, t, outside)
            return [(p + 50.0 * (w - a) + _leak(a, o)) / 200000.0, (50.0 * (a - w) + 20.0 * (o - w)) / 2000000.0]

        sol = scipy.integrate.solve_ivp(rhs, (0.0, t[-1]), [20.0, 20.0], t_eval=t, max_step=30.0, rtol=1e-8, atol=1e-8)
        y = sol.y[0] + rng.normal(0.0, 0.05, t.size)
        pd.DataFrame({"time": t, "air.T": y, "heater.P": power, "outside.T": outside}).to_csv(tmp_path / f"r{i}.csv", index=False)
        lines.append(f"  - id: r{i}\n    file: r{i}.csv\n    role: {'test' if i == 3 else 'train'}\n")
    (conf / "data" / "room.yaml").write_text(f"name: room\nroot: {tmp_path}\ntime_column: time\n"
                                            "validation_fraction: 0.2\nexperiments:\n" + "".join(lines))
    return tmp_path


def test_warm_start_recovers_the_missing_term_of_the_measured_equation(room_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(room_project)
    cfg = compose(["model=room", "data=room", "ude.width=16", "ude.depth=1"], user_config_dir=room_project / "conf")
    problem = load_problem(cfg)
    assert measured_states(problem) == [(0, 0)]
    ref = reference(problem, cfg)
    torch.manual_seed(0)
    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, ref), problem.dtype)
    before = evaluate(hybrid, problem, cfg)
    forced = forced_trajectories(problem, ref.batch, hybrid, 30.0)
    assert forced is not None and forced.measured == [0]
    stats = fit_network(hybrid, problem, ref.batch, forced, iterations=400, window=20)
    assert 0.0 < stats["warm.r2"] <= 1.0, stats  # R² against the noisy rate mismatch: noise bounds it
    # the correction of the air equation, in W, is the concealed ventilation loss
    v = forced.valid
    u, x = forced.states[v], forced.inputs[v]
    with torch.no_grad():
        corr = hybrid.corrections(u, x, ref.batch.params[:1].expand(u.shape[0], -1))
    names = problem.model.input_names
    true = _leak(u[:, 0].numpy(), x[:, names.index("outside.T")].numpy())
    watts = 200000.0 * corr[:, 0].numpy()
    # its size within 15 % (RMS) and its variation followed (the rate mismatch is noisy: r, not R² ≈ 1)
    assert np.sqrt(np.mean((watts - true) ** 2)) < 0.15 * np.abs(true).mean()
    assert np.corrcoef(watts, true)[0, 1] > 0.6
    # the hidden wall equation is left (nearly) alone, in W of its own balance
    assert np.abs(2000000.0 * corr[:, 1].numpy()).mean() < 0.1 * np.abs(true).mean()
    after = evaluate(hybrid, problem, cfg)
    assert after["val.rmse"] < 0.5 * before["val.rmse"], (before["val.rmse"], after["val.rmse"])
    assert after["test.rmse"] < 0.5 * before["test.rmse"], (before["test.rmse"], after["test.rmse"])


def test_no_warm_start_when_no_output_is_a_state(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``measured_states`` only pairs outputs that are plain states (the oscillator's x is one)."""
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    assert measured_states(problem) == [(0, 0)]


def test_formulas_are_judged_by_the_recordings(room_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``symbolic.select=recorded``: against the recorded mismatch of the air equation, the
    catalogue's one-constant conductance to outside beats a constant and a wrong pairing, and a
    5-constant polynomial that explains no more loses on the BIC."""
    import sympy as sp

    from physmend.symbolic.choice import catalogue_candidates, choose_by_recordings
    from physmend.symbolic import Candidate, ParetoFront
    from physmend.ude.rates import recorded_rates

    monkeypatch.chdir(room_project)
    cfg = compose(["model=room", "data=room", "ude.width=8", "ude.depth=1"], user_config_dir=room_project / "conf")
    problem = load_problem(cfg)
    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, reference(problem, cfg)), problem.dtype)
    rates = recorded_rates(hybrid, problem, cfg, ["air.T", "wall.T"], 1800.0)
    assert rates is not None and set(rates.targets) == {"air.T"}  # the wall is not measured
    inputs = ["air.T", "wall.T", "outside.T"]
    units = {n: "degC" for n in inputs}
    cols = {n: rates.columns[n][rates.window // 2:][: rates.valid.shape[0]][rates.valid] for n in inputs}
    y = rates.targets["air.T"][rates.valid]
    cands = catalogue_candidates(inputs, units, cols, y)
    a, o = sp.Symbol("air.T"), sp.Symbol("outside.T")
    poly = Candidate(expr=sp.Float(0.5) + sp.Float(14.0) * o - sp.Float(15.2) * a + sp.Float(1e-3) * a**2 + sp.Float(1e-4) * a * o,
                     complexity=15, mse=0.0, r2=0.0, text="polynomial")
    front = ParetoFront(backend="test", target="air.T", inputs=inputs, candidates=cands + [poly])
    i, why, scores = choose_by_recordings(rates, "air.T", front)
    chosen = front.candidates[i]
    assert "conductance" in chosen.text and {s.name for s in chosen.expr.free_symbols} == {"air.T", "outside.T"}, why
    alpha, r2 = scores[i]
    assert r2 > 0.8
    coef = float(abs(chosen.expr.subs({a: 1.0, o: 0.0}) - chosen.expr.subs({a: 0.0, o: 0.0})) * alpha)
    assert coef == pytest.approx(15.0, rel=0.2)  # W/K of the concealed ventilation


def test_models_of_one_warm_start_point_to_the_first() -> None:
    """Checks, chained starts and first evaluations are done once per warm start: each position
    points to the first with its key; a model without a key is its own."""
    from physmend.ude.warmstart import same_warm_start

    assert same_warm_start(["a", None, "b", "a", None, "b", "a"]) == [0, 1, 2, 0, 4, 2, 0]
    assert same_warm_start([]) == []
