"""Time settings derived from the data and the model (``auto``): the same rules at 10 ms and at 10 min."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from physmend.config import ConfigError, compose
from physmend.data import load_experiments
from physmend.modeling import Model, compile_model
from physmend.problem import Problem, dtype_of
from physmend.ude.timescale import TimeSettingError, resolve_times, time_scales

import torch

AUTO = ["train.step=auto", "train.segment_length=auto", "train.warm_window=auto", "symbolic.window=auto"]


def _problem(tmp_path: Path, dt: float, n: int, tau: float) -> Problem:
    """A first-order lag ``tau·der(y) = u − y`` sampled every ``dt`` s, ``n`` rows, two training records."""
    m = Model("lag")
    y = m.state("lag.y", start=0.0, unit="1")
    u = m.input("lag.u", unit="1")
    m.equation(m.parameter("lag.tau", tau, unit="s") * m.der(y), u - y, owner="lag")
    m.output("lag.y", y)
    model = m.simplify()
    t = np.arange(n) * dt
    rows = []
    for i in range(2):
        pd.DataFrame({"time": t, "lag.y": np.sin(t / (n * dt) * (3 + i)), "lag.u": np.ones(n)}).to_csv(
            tmp_path / f"r{i}.csv", index=False)
        rows.append({"id": str(i), "file": f"r{i}.csv", "role": "train"})
    data = {"name": "lag", "root": str(tmp_path), "experiments": rows}
    return Problem(model=model, compiled=compile_model(model), experiments=load_experiments(data, model),
                   dtype=torch.float64)


@pytest.mark.parametrize("dt", [0.01, 600.0])
def test_settings_follow_the_sampling_interval(tmp_path: Path, dt: float) -> None:
    problem = _problem(tmp_path, dt, 2000, tau=100 * dt)
    scales = time_scales(problem)
    assert scales.sample == pytest.approx(dt)
    assert scales.fastest == pytest.approx(100 * dt, rel=1e-4)
    cfg = resolve_times(compose(AUTO), problem)
    assert cfg.train.step == pytest.approx(dt / 2)
    assert cfg.train.segment_length == pytest.approx(60 * dt)
    assert cfg.train.warm_window == pytest.approx(10 * dt)
    assert cfg.symbolic.window == pytest.approx(30 * dt)


def test_a_short_record_caps_segments_and_windows(tmp_path: Path) -> None:
    problem = _problem(tmp_path, 1.0, 40, tau=10.0)  # 40 samples of dimensionless time
    record = time_scales(problem).record
    cfg = resolve_times(compose(AUTO), problem)
    assert cfg.train.segment_length == pytest.approx(record / 4)
    assert cfg.train.warm_window == pytest.approx(max(2.0, record / 10))
    assert cfg.symbolic.window == pytest.approx(max(3.0, record / 10))
    assert (cfg.train.segment_length / cfg.train.step) == pytest.approx(round(cfg.train.segment_length / cfg.train.step))


def test_a_stiff_model_gets_a_step_within_rk4_stability(tmp_path: Path) -> None:
    problem = _problem(tmp_path, 1.0, 500, tau=0.05)  # time constant 20x shorter than the sampling interval
    cfg = resolve_times(compose(AUTO), problem)
    assert cfg.train.step <= 2.0 * 0.05 + 1e-12
    assert cfg.train.step * (1 / 0.05) < 2.785  # inside RK4's stability interval on the real axis


def test_given_numbers_win_and_impossible_ones_are_clear_errors(tmp_path: Path) -> None:
    problem = _problem(tmp_path, 0.01, 300, tau=1.0)
    cfg = resolve_times(compose([*AUTO, "train.step=0.002", "train.segment_length=0.5"]), problem)
    assert (cfg.train.step, cfg.train.segment_length) == (0.002, 0.5)
    with pytest.raises(TimeSettingError, match=r"train.step = 30 is not shorter than the shortest training record"):
        resolve_times(compose([*AUTO, "train.step=30"]), problem)
    with pytest.raises(TimeSettingError, match=r"train.segment_length = 3600 is longer than the shortest training record"):
        resolve_times(compose([*AUTO, "train.segment_length=3600"]), problem)
    with pytest.raises(ConfigError, match=r"train.segment_samples must be a whole number ≥ 1, but got -3"):
        compose([*AUTO, "train.segment_samples=-3"])  # refused when the configuration is composed


def test_a_plan_over_the_memory_budget_is_refused_in_one_line(tmp_path: Path) -> None:
    from physmend.ude import train

    problem = _problem(tmp_path, 0.01, 2000, tau=1.0)
    cfg = compose([*AUTO, "train.memory_limit_gib=0.001", "train.epochs=1"])
    with pytest.raises(TimeSettingError) as err:
        train(cfg, problem)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith("the training plan needs about ") and "more than train.memory_limit_gib=0.001" in message
    assert "RK4 steps of 0.005" in message
