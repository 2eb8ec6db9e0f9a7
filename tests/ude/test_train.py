"""UDE training on a small non-thermal model: real torch training, honest evaluation, reload."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from physmend.config import ConfigError, compose
from physmend.problem import load_problem
from physmend.ude import TrainingDiverged, UDEConfigError, evaluate, load_hybrid, reference, train
from physmend.ude.hybrid import HybridModel
from physmend.ude.spec import build_spec
from physmend.ude.shooting import chained_starts, plan_shooting, rk4_segments

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=60",
        "train.eval_every=20", "train.lr=0.02", "ude.width=16", "ude.depth=1", "train.patience=0",
        "simulate.rtol=1e-6", "simulate.atol=1e-7"]


def _cfg(project: Path, *extra: str):  # noqa: ANN202
    return compose([*TINY, *extra], user_config_dir=project / "my_conf")


def test_training_beats_the_model_as_written_and_reloads(user_project: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.chdir(user_project)
    cfg = _cfg(user_project)
    problem = load_problem(cfg)
    seen: list[tuple[int, float]] = []
    result = train(cfg, problem, report=lambda epoch, m: seen.append((epoch, m["val.rmse"])))
    epochs = [e for e, _ in seen]
    assert epochs[:4] == [0, 20, 40, 60]  # 0: the warm start (the output is a state)
    assert all(e > 60 for e in epochs[4:])  # then the L-BFGS polish's checkpoints (train.polish)
    # the model as written, evaluated the same way (an untrained correction is ~0 but not exactly)
    ref = reference(problem, cfg)
    y_ref = problem.compiled.outputs(ref.states, ref.inputs, ref.batch.params[None])
    mask = torch.isfinite(ref.batch.obs[:, :2, 0]) & (ref.batch.t[:, None] >= ref.batch.split_time[None, :2])
    ref_val = float((y_ref[:, :2, 0] - ref.batch.obs[:, :2, 0])[mask].pow(2).mean().sqrt())
    assert result.val_rmse < 0.7 * ref_val, (result.val_rmse, ref_val)
    assert result.metrics["val.rmse"] == result.val_rmse
    assert {"train.rmse", "test.rmse", "rmse.run3.cart.x", "estimate.damper.c"} <= set(result.metrics)
    assert 0.0 <= result.metrics["estimate.damper.c"] <= 5.0
    assert set(result.figures) == {"plots/fit_run1.png", "plots/fit_run2.png", "plots/fit_run3.png"}
    # artifacts are plain files; a rebuilt model reproduces the validation metric
    for rel, content in result.artifacts.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    rebuilt = load_hybrid(cfg, load_problem(cfg), tmp_path)
    again = evaluate(rebuilt, problem, cfg)
    assert again["val.rmse"] == pytest.approx(result.val_rmse, rel=1e-9)


def test_bad_settings_are_clear_errors(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = _cfg(user_project, "ude.corrected=[wheel.*]")
    with pytest.raises(UDEConfigError, match=r"ude.corrected: pattern 'wheel.\*' matches no name"):
        train(cfg, load_problem(cfg))
    cfg = _cfg(user_project, "ude.activation=swish")
    with pytest.raises(UDEConfigError, match=r"ude.activation must be one of .* but got 'swish'"):
        train(cfg, load_problem(cfg))
    with pytest.raises(ConfigError, match=r"train.segment_starts must be one of \['chained', 'forced'\], but got 'sideways'"):
        _cfg(user_project, "train.segment_starts=sideways")  # refused when the configuration is composed


def test_chained_segment_starts_leave_no_gaps(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each segment after an experiment's first starts exactly where the one before it ends; first
    segments keep their known initial states; a model whose chain leaves the finite range keeps its starts."""
    monkeypatch.chdir(user_project)
    cfg = _cfg(user_project)
    problem = load_problem(cfg)
    ref = reference(problem, cfg)
    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, ref), problem.dtype)
    plan = plan_shooting(problem, ref.batch, cfg)
    has = plan.next_of >= 0
    assert int(has.sum()) >= 2 and int(plan.first.sum()) >= 2  # several experiments, several segments each
    u0 = ref.batch.u0[plan.exp_index] + 0.3 * torch.randn(plan.starts.shape[0], len(problem.model.state_names), dtype=problem.dtype)
    rhs = hybrid.rhs(hybrid.parameters_for(ref.batch.params[plan.exp_index]))
    with torch.no_grad():
        gaps_before = (rk4_segments(rhs, u0, plan)[-1][has] - u0[plan.next_of[has]]).abs().max()
    chained = chained_starts(rhs, u0, plan)
    end = rk4_segments(rhs, chained, plan)[-1]
    torch.testing.assert_close(chained[plan.next_of[has]], end[has], rtol=0, atol=1e-12)
    assert float(gaps_before) > 1e-3
    torch.testing.assert_close(chained[plan.first], u0[plan.first], rtol=0, atol=0)
    # measured-state columns (keep) stay at their given starts; the others are chained
    part = chained_starts(rhs, u0, plan, keep=[0])
    torch.testing.assert_close(part[:, 0], u0[:, 0], rtol=0, atol=0)
    end = rk4_segments(rhs, part, plan)[-1]
    torch.testing.assert_close(part[plan.next_of[has], 1:], end[has, 1:], rtol=0, atol=1e-12)
    # two stacked models (rows model-major): the second blows up and keeps its own starts
    two = torch.cat([u0, u0])
    blow = lambda u, x: torch.cat([rhs(u[..., : u0.shape[0], :], x[..., : u0.shape[0], :]),  # noqa: E731
                                   torch.full_like(u[..., u0.shape[0]:, :], float("inf"))], dim=-2)
    stacked_plan = dataclasses.replace(plan, x_half=plan.x_half.repeat(1, 2, 1))
    out = chained_starts(blow, two, stacked_plan, models=2)
    torch.testing.assert_close(out[: u0.shape[0]], chained, rtol=0, atol=1e-12)
    torch.testing.assert_close(out[u0.shape[0]:], u0, rtol=0, atol=0)


def test_divergence_is_reported_not_hidden(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    bad = ["train.lr=1.0e6", "train.epochs=20", "train.eval_every=5", "ude.output_scale=100.0"]
    cfg = _cfg(user_project, *bad, "train.warm_start=none")
    with pytest.raises(TrainingDiverged, match=r"non-finite|failed"):
        train(cfg, load_problem(cfg))
    # a failed checkpoint is dropped, not the model: the warm start stays the best, and the count says so
    cfg = _cfg(user_project, *bad)
    result = train(cfg, load_problem(cfg))
    failed = [r["epoch"] for r in result.history if r["val.rmse"] == float("inf")]
    assert failed and result.metrics["checkpoints.failed"] == len(failed)
    assert result.val_rmse == pytest.approx(result.history[0]["val.rmse"], rel=1e-6)  # test experiments solved apart


def test_a_test_experiment_that_fails_to_simulate_does_not_fail_the_model(user_project: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Held-out data decide nothing: a test recording whose input drives the hybrid off the finite
    range gives NaN test metrics, while the model (chosen on training and validation) survives."""
    import pandas as pd

    monkeypatch.chdir(user_project)
    cfg = _cfg(user_project, "train.epochs=20", "train.eval_every=10")
    plain = train(cfg, load_problem(cfg))
    test_file = user_project / "recordings" / "run3.csv"
    frame = pd.read_csv(test_file)
    frame["motor.F"] = 1e150  # within float64 sums (the data check), but the hybrid leaves its box: run3's solve fails
    frame.to_csv(test_file, index=False)
    result = train(cfg, load_problem(cfg))
    assert result.val_rmse == pytest.approx(plain.val_rmse, rel=1e-4)  # to solver tolerance (the reference is one batched solve)
    assert result.metrics["test.failed"] == 1.0
    assert result.metrics["test.rmse"] != result.metrics["test.rmse"]  # NaN
    assert plain.metrics["test.rmse"] == plain.metrics["test.rmse"]
    assert plain.metrics["test.failed"] == 0.0
    frame["motor.F"] = 0.0
    frame.to_csv(test_file, index=False)
    data_cfg = user_project / "my_conf" / "data" / "oscillator.yaml"
    data_cfg.write_text(data_cfg.read_text().replace("cart.x0: 0.2", "cart.x0: 1.0e150"))  # the solve itself fails
    again = _cfg(user_project, "train.epochs=20", "train.eval_every=10")
    failing = train(again, load_problem(again))
    assert failing.val_rmse == pytest.approx(plain.val_rmse, rel=1e-4)
    assert failing.metrics["test.failed"] == 1.0
