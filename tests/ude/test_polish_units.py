"""Corrections in the equation's own units (``ude.units``) and the L-BFGS polish (``train.polish``)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude import TrainResult, train
from physmend.ude.hybrid import HybridModel
from physmend.ude.reference import reference
from physmend.ude.spec import build_spec
from physmend.ude.stack import train_stack
from physmend.ude.timescale import resolve_times

# the oscillator of tests/conftest.py (mass·der(v) = force), records cut short, an explicit solver
BASE = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=4",
        "train.eval_every=2", "train.patience=0", "train.warm_start=none", "simulate=explicit",
        "simulate.rtol=1e-5", "simulate.atol=1e-6"]


@pytest.fixture
def short_project(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for path in (user_project / "recordings").glob("*.csv"):
        frame = pd.read_csv(path)
        frame[frame["t_s"] < frame["t_s"].iloc[0] + 30.0].to_csv(path, index=False)
    monkeypatch.chdir(user_project)
    yield user_project
    import matplotlib.pyplot as plt

    plt.close("all")


def _hybrid(project: Path, *extra: str) -> tuple[HybridModel, object]:
    cfg = compose([*BASE, *extra], user_config_dir=project / "my_conf")
    problem = load_problem(cfg)
    ref = reference(problem, cfg)
    cfg = resolve_times(cfg, problem, ref)
    return HybridModel(problem.compiled, build_spec(cfg, problem, ref), problem.dtype), problem


@pytest.mark.parametrize("units", ["equation", "state"])
def test_a_correction_in_equation_units_is_divided_by_the_equations_coefficient(short_project: Path, units: str) -> None:
    # the network does not see the parameters: whatever changes with them comes from the units rule
    hybrid, problem = _hybrid(short_project, f"ude.units={units}", "ude.inputs.parameters=[]")
    model = problem.model
    coefs = {n: model.der_coefficient.get(n, 1) for n in hybrid.spec.corrected}
    carrier = next(n for n, c in coefs.items() if getattr(c, "is_Symbol", False))  # m·der(v) = …: m
    mass = model.parameter_names.index(str(coefs[carrier]))
    col = hybrid.spec.corrected.index(carrier)
    p1 = torch.tensor([list(problem.experiments[0].parameters)], dtype=problem.dtype)
    p2 = p1.clone()
    p2[0, mass] *= 2.0
    u = torch.randn(5, 1, len(model.state_names), dtype=problem.dtype)
    x = torch.zeros(5, 1, len(problem.compiled.input_names), dtype=problem.dtype)
    with torch.no_grad():
        for layer in hybrid.net:  # a network whose output is not zero
            if isinstance(layer, torch.nn.Linear):
                layer.weight.normal_()
                layer.bias.normal_()
        c1, c2 = hybrid.corrections(u, x, p1)[..., col], hybrid.corrections(u, x, p2)[..., col]
    assert bool((c1.abs() > 0).all())
    expected = 0.5 if units == "equation" else 1.0  # twice the mass: half the rate for the same force
    torch.testing.assert_close(c2, expected * c1)
    assert hybrid.spec.units == units


def test_polish_lowers_the_training_loss_and_its_checkpoints_keep_judging(short_project: Path) -> None:
    cfg = compose([*BASE, "ude.width=8", "train.polish=2"], user_config_dir=short_project / "my_conf")
    problem = load_problem(cfg)
    result = train(cfg, problem)
    epochs = [r["epoch"] for r in result.history]
    assert epochs[:2] == [2.0, 4.0] and len(epochs) > 2 and all(e > 4 for e in epochs[2:])  # 8 iterations after Adam
    adam_end = result.history[1]["loss"]  # the multiple-shooting loss both minimise
    assert min(r["loss"] for r in result.history[2:]) < 0.9 * adam_end
    # the kept model is the best checkpoint by validation RMSE, polish or not
    assert result.val_rmse == pytest.approx(min(r["val.rmse"] for r in result.history), rel=1e-6)


def test_a_stack_polishes_each_model_within_its_own_shape(short_project: Path) -> None:
    """Different widths and depths share one padded stack: under L-BFGS the padded entries stay zero,
    so each model's stacked checkpoints are what the model alone computes."""
    trials = [["seed=1", "ude.width=8", "ude.depth=1", "ude.activation=softplus"],
              ["seed=2", "ude.width=12", "ude.depth=2", "ude.activation=gelu"]]
    cfgs = [compose([*BASE, "train.polish=2", *t], user_config_dir=short_project / "my_conf") for t in trials]
    problem = load_problem(cfgs[0])
    results = train_stack(cfgs, problem, figures=False)
    for cfg, result in zip(cfgs, results):
        assert isinstance(result, TrainResult), result
        assert result.hybrid.spec.widths == [int(cfg.ude.width)] * int(cfg.ude.depth)
        polished = [r for r in result.history if r["epoch"] > 4]
        assert polished, result.history
        assert min(r["loss"] for r in polished) < result.history[1]["loss"]
        # the solo evaluation of the written-back best model equals its stacked checkpoint
        assert result.val_rmse == pytest.approx(min(r["val.rmse"] for r in result.history), rel=1e-3)


def test_an_estimated_capacity_does_not_rescale_the_network(short_project: Path) -> None:
    """With the mass estimated, the force the network adds is converted to a rate by the mass as
    written: moving the estimate changes the physics, never the network's term (the two cannot
    trade one scale for the other)."""
    source = short_project / "oscillator.py"
    text = source.read_text()
    assert 'm.parameter("cart.mass", 2.0, unit="kg")' in text
    source.write_text(text.replace('m.parameter("cart.mass", 2.0, unit="kg")',
                                   'm.parameter("cart.mass", 2.0, unit="kg", uncertain=True, bounds=(1.0, 4.0))'))
    hybrid, problem = _hybrid(short_project, "ude.inputs.parameters=[]")
    assert "cart.mass" in hybrid.spec.estimated and hybrid.coefficients is not None
    col = hybrid.spec.corrected.index("cart.v")
    p = torch.tensor([list(problem.experiments[0].parameters)], dtype=problem.dtype)
    u = torch.randn(4, 1, len(problem.model.state_names), dtype=problem.dtype)
    x = torch.zeros(4, 1, len(problem.compiled.input_names), dtype=problem.dtype)
    with torch.no_grad():
        hybrid.net[-1].bias.fill_(1.0)
        before = hybrid.corrections(u, x, hybrid.parameters_for(p))[..., col]
        hybrid.est_raw.add_(2.0)  # the mass estimate moves well away from 2 kg
        assert abs(hybrid.estimates()["cart.mass"] - 2.0) > 0.5
        after = hybrid.corrections(u, x, hybrid.parameters_for(p))[..., col]
    torch.testing.assert_close(after, before)


def test_the_noise_fit_is_the_fit_term_of_white_sensor_noise() -> None:
    """``noise_fit``: mean over training samples of (σ/spread)², σ from each record's second differences."""
    from types import SimpleNamespace

    from physmend.ude.shooting import noise_fit

    gen = torch.Generator().manual_seed(0)
    t = torch.linspace(0.0, 100.0, 2001, dtype=torch.float64)
    smooth = torch.stack([torch.sin(t / 7.0), 3.0 * torch.cos(t / 11.0)], -1)  # (T, k)
    sigma = torch.tensor([0.01, 0.2], dtype=torch.float64)
    obs = (smooth + sigma * torch.randn(t.shape[0], 2, generator=gen, dtype=torch.float64))[:, None, :]  # (T, 1, k)
    spread = torch.tensor([0.5, 2.0], dtype=torch.float64)
    mask = torch.ones(t.shape[0], 1, dtype=torch.bool)
    expected = float(((sigma / spread) ** 2).mean())
    assert noise_fit(SimpleNamespace(t=t, obs=obs), mask, spread) == pytest.approx(expected, rel=0.1)
    # only the masked (training) samples count; too few samples: no estimate
    none = torch.zeros_like(mask)
    assert torch.isnan(torch.tensor(noise_fit(SimpleNamespace(t=t, obs=obs), none, spread)))


def test_a_fit_at_the_noise_is_not_polished(short_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """L-BFGS runs only while the training fit is above ``AT_NOISE`` × the noise's: with the bar raised
    above any fit, ``train`` and a stack stop after Adam (no checkpoint past its last epoch)."""
    from physmend.ude import polish

    assert polish.worth_polishing(3.0, 1.0) and not polish.worth_polishing(1.5, 1.0)
    assert polish.worth_polishing(float("nan"), 1.0) and polish.worth_polishing(1.0, float("nan"))
    assert polish.fit_at([{"val.rmse": 2.0, "fit_loss": 0.3}, {"val.rmse": 1.0, "fit_loss": 0.1}], 1.0) == 0.1
    cfg = compose([*BASE, "ude.width=8", "train.polish=2"], user_config_dir=short_project / "my_conf")
    problem = load_problem(cfg)
    monkeypatch.setattr(polish, "AT_NOISE", 1e12)
    result = train(cfg, problem)
    assert [r["epoch"] for r in result.history] == [2.0, 4.0]
    results = train_stack([cfg, compose([*BASE, "ude.width=12", "train.polish=2", "seed=3"],
                                        user_config_dir=short_project / "my_conf")], problem, figures=False)
    for r in results:
        assert isinstance(r, TrainResult) and [h["epoch"] for h in r.history] == [2.0, 4.0], r
