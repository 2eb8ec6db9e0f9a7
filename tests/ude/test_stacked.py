"""Several hybrid models trained in one batched solve: each must be exactly its own trial."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from physmend.config import ConfigError, compose
from physmend.problem import load_problem
from physmend.ude import TrainingDiverged, TrainResult, UDEConfigError, evaluate, load_hybrid, train
from physmend.settings import training_settings
from physmend.ude.timescale import resolve_settings
from physmend.ude.stack import stack_key, train_stack
from physmend.ude.stack.members import prepare
from physmend.ude.stack.solve import Stack
from physmend.ude.metrics import evaluate_with, checkpoint_problem
from physmend.ude.reference import clocked, solver_options, reference
from physmend.ude.shooting import plan_shooting
from physmend.ude.warmstart import WARM_STATS, forget_warm_starts

# the oscillator of tests/conftest.py; an explicit solver keeps whole-trajectory evaluations short
BASE = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=4",
        "train.eval_every=2", "train.patience=0",
        "train.polish=0", "simulate=explicit", "simulate.rtol=1e-5", "simulate.atol=1e-6"]
# three trials that share the solve but nothing else
TRIALS = [
    ["seed=1", "ude.width=8", "ude.depth=1", "ude.activation=tanh", "train.lr=0.02"],
    ["seed=2", "ude.width=16", "ude.depth=2", "ude.activation=softplus", "train.lr=0.01", "train.weight_decay=1e-3"],
    ["seed=3", "ude.width=12", "ude.depth=3", "ude.activation=gelu", "train.lr=0.005", "ude.output_scale=0.05"],
]


@pytest.fixture(autouse=True)
def _close_figures():  # noqa: ANN202 - every TrainResult carries fit figures
    yield
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.fixture
def short_project(user_project: Path) -> Path:
    """The oscillator project with records cut to their first 30 s (evaluations cost per input sample)."""
    for path in (user_project / "recordings").glob("*.csv"):
        frame = pd.read_csv(path)
        frame[frame["t_s"] < frame["t_s"].iloc[0] + 30.0].to_csv(path, index=False)
    return user_project


def _cfg(project: Path, *extra: str, warm_start: str = "auto"):  # noqa: ANN202
    cfg = compose([*BASE, *extra], user_config_dir=project / "my_conf")
    OmegaConf.update(cfg, "train.warm_start", warm_start, force_add=True)
    OmegaConf.update(cfg, "train.warm_iterations", 100, force_add=True)  # a shorter warm start
    OmegaConf.update(cfg, "train.warmup_epochs", 2, force_add=True)  # and a learning-rate ramp after it
    return cfg


def test_each_model_of_a_stack_trains_exactly_as_alone(short_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                      tmp_path: Path) -> None:
    monkeypatch.chdir(short_project)
    cfgs = [_cfg(short_project, *t) for t in TRIALS]
    assert len({stack_key(c) for c in cfgs}) == 1
    problem = load_problem(cfgs[0])
    seen: list[tuple[int, int]] = []
    results = train_stack(cfgs, problem, report=lambda i, epoch, row: seen.append((i, epoch)))
    # the warm start is evaluated (epoch 0) as train() does, then every eval_every epochs
    assert sorted(seen) == [(i, e) for i in range(3) for e in (0, 2, 4)]
    for cfg, result in zip(cfgs, results):
        assert isinstance(result, TrainResult), result
        forget_warm_starts()  # the model alone fits its own warm start (not the stack's stored one)
        alone = train(cfg, problem)
        # own architecture, exactly: the same state_dict keys and shapes as a model trained alone
        ours, theirs = result.hybrid.state_dict(), alone.hybrid.state_dict()
        assert {k: v.shape for k, v in ours.items()} == {k: v.shape for k, v in theirs.items()}
        assert result.hybrid.spec.widths == [int(cfg.ude.width)] * int(cfg.ude.depth)
        # The same weights: batched products (baddbmm over padded tensors) round differently from
        # nn.Linear, so agreement is to a few ulps, not bit for bit.
        for key in theirs:
            torch.testing.assert_close(ours[key], theirs[key], rtol=1e-9, atol=1e-12, msg=key)
        # final metrics come from the model's own solo evaluation, as in train()
        assert result.val_rmse == pytest.approx(alone.val_rmse, rel=1e-6)
        assert set(result.metrics) == set(alone.metrics)
        for key, value in alone.metrics.items():
            assert result.metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-12), key
        assert [r["epoch"] for r in result.history] == [r["epoch"] for r in alone.history] == [0.0, 2.0, 4.0]
        for ours_row, alone_row in zip(result.history[1:], alone.history[1:]):
            # training losses are the same computation, row for row
            assert ours_row["loss"] == pytest.approx(alone_row["loss"], rel=1e-9)
            assert ours_row["fit_loss"] == pytest.approx(alone_row["fit_loss"], rel=1e-9)
        for ours_row, alone_row in zip(result.history, alone.history):
            # checkpoint metrics come from one adaptive solve of all models, whose shared step sizes
            # differ from a solo solve's: they agree to the solver tolerance, not to rounding
            assert ours_row["val.rmse"] == pytest.approx(alone_row["val.rmse"], rel=1e-3)
        assert set(result.figures) == set(alone.figures)
    # artifacts are train()'s: a reloaded model reproduces the metric
    result = results[1]
    assert isinstance(result, TrainResult)
    for rel, content in result.artifacts.items():
        path = tmp_path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
    rebuilt = load_hybrid(cfgs[1], problem, tmp_path)
    assert evaluate(rebuilt, problem, cfgs[1])["val.rmse"] == pytest.approx(result.val_rmse, rel=1e-9)


def test_a_warm_start_is_fitted_once_per_network_and_reused(short_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Trials that differ only in training settings (learning rate, weight decay) share their warm
    start: it is fitted once per process and reused, and reusing it changes nothing."""
    monkeypatch.chdir(short_project)
    forget_warm_starts()
    same = ["seed=1", "ude.width=8", "ude.depth=1", "ude.activation=tanh"]
    cfgs = [_cfg(short_project, *same, "train.lr=0.02"), _cfg(short_project, *same, "train.lr=0.005", "train.weight_decay=1e-3"),
            _cfg(short_project, *TRIALS[1])]
    problem = load_problem(cfgs[0])
    before = dict(WARM_STATS)
    first = train_stack(cfgs, problem, figures=False)
    assert WARM_STATS["fitted"] - before["fitted"] == 2 and WARM_STATS["reused"] - before["reused"] == 1
    assert WARM_STATS["derived_reused"] == before["derived_reused"]  # one stack: nothing stored before it
    again = train_stack(cfgs, problem, figures=False)
    assert WARM_STATS["fitted"] - before["fitted"] == 2 and WARM_STATS["reused"] - before["reused"] == 4
    # the second stack also reuses each warm start's checkpoint evaluation and chained segment starts
    assert WARM_STATS["derived_reused"] - before["derived_reused"] == 2 * len(cfgs)
    # other segments: the evaluation is reused, the chained starts (which depend on them) are not
    longer = [c.copy() for c in cfgs]
    for c in longer:
        c.train.segment_length = 6.0
    reused = WARM_STATS["derived_reused"]
    train_stack(longer, problem, figures=False)
    assert WARM_STATS["derived_reused"] - reused == len(cfgs)
    for a, b in zip(first, again):
        assert isinstance(a, TrainResult) and isinstance(b, TrainResult)
        assert a.val_rmse == b.val_rmse and repr(a.history) == repr(b.history)  # repr: NaN losses at epoch 0
    # the two trials that share a network started from the same warm start, then trained differently
    assert repr(first[0].history[0]) == repr(first[1].history[0]) and first[0].history[-1] != first[1].history[-1]
    # train() alone reuses it as well, with the same outcome
    alone = train(cfgs[2], problem)
    assert WARM_STATS["fitted"] - before["fitted"] == 2
    assert alone.history[0]["val.rmse"] == pytest.approx(first[2].history[0]["val.rmse"], rel=1e-3)


def test_padded_units_stay_zero_and_rows_match_their_own_network(short_project: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(short_project)
    # sigmoid and softplus are non-zero at 0: padded units are active, only their weights keep them out
    trials = [["seed=4", "ude.width=3", "ude.depth=1", "ude.activation=sigmoid"],
              ["seed=5", "ude.width=7", "ude.depth=3", "ude.activation=softplus"],
              ["seed=6", "ude.width=5", "ude.depth=2", "ude.activation=tanh"]]
    cfgs = [_cfg(short_project, *t, "train.lr=0.1", "train.weight_decay=0.5", warm_start="none") for t in trials]
    problem = load_problem(cfgs[0])
    ref = reference(problem, cfgs[0])
    plan = plan_shooting(problem, ref.batch, cfgs[0])
    members = [prepare(resolve_settings(training_settings(c), problem, ref), problem, ref, plan, i) for i, c in enumerate(cfgs)]
    stack = Stack(members, problem, ref, plan, cfgs[0])
    masked = [(p, mk) for p, mk, _, _ in stack.params if mk is not None]
    assert len(masked) == 2 * 4 - 1  # weights and biases of 3 hidden layers and the output layer (its bias is not padded)
    for _ in range(3):
        loss, _ = stack.losses()
        stack.step(loss, torch.full((3,), 0.1, dtype=problem.dtype), torch.arange(3))
    for p, mk in masked:
        assert bool((p.detach()[~mk] == 0).all())
        assert bool((p.detach()[mk] != 0).any())
    for (p, mk, _, _), m1, m2 in zip(stack.params, stack.exp_avg, stack.exp_avg_sq):
        if mk is not None:
            assert bool((m1[~mk] == 0).all()) and bool((m2[~mk] == 0).all())
    # every stack row computes what its own (unpadded) model computes
    u = ref.states[::50, :2]  # (T', 2 experiments, n)
    x = ref.inputs[::50, :2]
    p = ref.batch.params[:2]
    rows = stack._corrections(stack.net, 3, u.repeat(1, 3, 1), x.repeat(1, 3, 1), p.repeat(3, 1), stack._coef(p.repeat(3, 1)))
    for i, mem in enumerate(stack.members):
        stack.write_back(i)
        with torch.no_grad():
            own = mem.hybrid.corrections(u, x, p)
        torch.testing.assert_close(rows[:, 2 * i:2 * i + 2].detach(), own, rtol=1e-12, atol=1e-15)
    # one batched evaluation of all three gives each model's own metrics (to the solver tolerance:
    # the shared adaptive solve takes steps no single model would)
    # Checkpoints simulate the train and validation experiments only; `full` adds the test ones.
    checkpoints, final = stack.evaluate([0, 1, 2], solver_options(cfgs[0])), stack.evaluate([0, 1, 2], solver_options(cfgs[0]), full=True)
    assert any(e.role == "test" for e in problem.experiments)
    for i, mem in enumerate(stack.members):
        stack.write_back(i)
        for batched, of in ((checkpoints, checkpoint_problem(problem)), (final, problem)):
            alone, _, _ = evaluate_with(mem.hybrid, of, solver_options(cfgs[0]))
            got = batched[i][0]
            assert set(got) == set(alone)
            for key, value in alone.items():
                assert got[key] == pytest.approx(value, rel=1e-4), key
        assert "test.rmse" in final[i][0] and "test.rmse" not in checkpoints[i][0]
    # a failed batched solve falls back to solving each model alone, each failure its own outcome
    outcomes = stack.evaluate([0, 2], {**solver_options(cfgs[0]), "method": "no-such-method"})
    assert len(outcomes) == 2 and all(isinstance(o, TrainingDiverged) and "no-such-method" in str(o) for o in outcomes)


@pytest.mark.parametrize("record", ["every other sample", "half a sample later"])
def test_checkpoints_of_records_on_different_clocks_take_only_their_own_steps(
        short_project: Path, monkeypatch: pytest.MonkeyPatch, record: str) -> None:
    """Records sampled at different times take only their own steps: solved apart per time grid
    where a clock per row would not pay (run2 on every other time of run1), in one solve with a clock
    per row where it does (run2 between run1's times); each model still gets the metrics its own
    evaluation gives."""
    monkeypatch.chdir(short_project)
    path = short_project / "recordings" / "run2.csv"
    frame = pd.read_csv(path)
    if record == "every other sample":
        frame = frame.iloc[::2]  # run2 every 0.2 s, run1 every 0.1 s
    else:
        # times count from each record's start: every row but the first half a sample later
        frame.loc[frame.index[1:], "t_s"] += 0.5 * float(frame["t_s"].diff().median())
    frame.to_csv(path, index=False)
    cfgs = [_cfg(short_project, *t, warm_start="none") for t in TRIALS[:2]]
    problem = load_problem(cfgs[0])
    ref = reference(problem, cfgs[0])
    plan = plan_shooting(problem, ref.batch, cfgs[0])
    stack = Stack([prepare(resolve_settings(training_settings(c), problem, ref), problem, ref, plan, i) for i, c in enumerate(cfgs)],
                  problem, ref, plan, cfgs[0])
    checked = checkpoint_problem(problem)
    assert [e.id for e in checked.experiments] == ["run1", "run2"]
    assert [exps for exps, _, _ in stack.parts] == [[0], [1]]
    # tight tolerances: the union-of-times solve and the separate ones step differently, and at
    # the default rtol their answers may differ by more than the rel 1e-4 compared here; a solver
    # with a clock per row
    sim = {**solver_options(cfgs[0]), "method": "rodas4", "rtol": 1e-8, "atol": 1e-10}
    assert clocked(sim, stack.eval_batch) == (record == "half a sample later")
    checkpoints = stack.evaluate([0, 1], sim)
    for i, mem in enumerate(stack.members):
        stack.write_back(i)
        alone, _, _ = evaluate_with(mem.hybrid, checked, sim)
        got, y = checkpoints[i]
        assert set(got) == set(alone)
        for key, value in alone.items():
            assert got[key] == pytest.approx(value, rel=1e-4), key
        # outputs on the union of times: each record has values at each of its own times
        for b, e in enumerate(checked.experiments):
            own = torch.isfinite(stack.eval_batch.obs[:, b]).any(-1)
            assert int(own.sum()) == len(e.obs_time) and bool(torch.isfinite(y[own, b]).all())


def test_a_stopped_or_diverging_model_leaves_the_others_alone(short_project: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(short_project)

    class Pruned(Exception):
        pass

    cfgs = [_cfg(short_project, "train.epochs=6", *extra, warm_start="none") for extra in (
        ["seed=1", "train.lr=0.02"],
        ["seed=2", "train.lr=0.02"],
        ["seed=3", "ude.output_scale=1.0e200"],  # corrections overflow: the loss is not finite in epoch 1
    )]
    seen: list[tuple[int, int]] = []

    def report(i: int, epoch: int, row: dict[str, float]) -> None:
        seen.append((i, epoch))
        if i == 1 and epoch == 2:
            raise Pruned("trial 1 pruned at epoch 2")

    problem = load_problem(cfgs[0])
    results = train_stack(cfgs, problem, report=report, final_eval="batched", figures=False)
    assert isinstance(results[1], Pruned)
    assert isinstance(results[2], TrainingDiverged)
    # the training solve keeps states in a box about the data, so the overflow shows either in the
    # loss or when the whole trajectory is simulated; either way that model alone has diverged
    assert ("training loss became non-finite at epoch 1" in str(results[2])
            or "whole-trajectory simulation of the hybrid failed" in str(results[2])), str(results[2])
    ok = results[0]
    assert isinstance(ok, TrainResult)
    assert [r["epoch"] for r in ok.history] == [2.0, 4.0, 6.0]
    # final_eval="batched": the best checkpoint simulated again on every experiment (test ones too),
    # within solver tolerance of a solo evaluation
    assert ok.val_rmse == pytest.approx(min(r["val.rmse"] for r in ok.history), rel=1e-4)
    own = evaluate(ok.hybrid, problem, cfgs[0])
    assert set(own) == set(ok.metrics) - {"estimate.damper.c", "checkpoints.failed"}
    for key, value in own.items():
        assert ok.metrics[key] == pytest.approx(value, rel=1e-4), key
    assert {"train.rmse", "test.rmse", "estimate.damper.c"} <= set(ok.metrics) and ok.figures == {}
    # the survivor trained on, unchanged, after the others left the stack
    alone = train(cfgs[0], problem)
    for key, value in alone.hybrid.state_dict().items():
        torch.testing.assert_close(ok.hybrid.state_dict()[key], value, rtol=1e-9, atol=1e-12, msg=key)
    assert [r["loss"] for r in ok.history] == pytest.approx([r["loss"] for r in alone.history], rel=1e-9)
    assert [e for i, e in seen if i == 0] == [2, 4, 6]
    assert [e for i, e in seen if i == 1] == [2]
    assert [e for i, e in seen if i == 2] == []


def test_shared_settings_must_agree(short_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(short_project)
    a = _cfg(short_project, "seed=1", "ude.width=8")
    b = _cfg(short_project, "seed=2", "ude.width=16", "train.lr=0.1", "ude.activation=gelu")
    assert stack_key(a) == stack_key(b)
    assert stack_key(a, architecture=True) != stack_key(b, architecture=True)
    c = _cfg(short_project, "train.step=0.1")
    assert stack_key(a) != stack_key(c)
    with pytest.raises(UDEConfigError, match=r"same `train\.step`.* model 0 has 0\.05 and model 1 has 0\.1"):
        train_stack([a, c], None)  # type: ignore[arg-type]  # checked before the problem is used
    d = _cfg(short_project, "ude.corrected=[cart.v]")
    with pytest.raises(UDEConfigError, match=r"same `ude\.corrected`"):
        train_stack([a, b, d], None)  # type: ignore[arg-type]
    e = _cfg(short_project, "ude.depth=0")
    with pytest.raises(UDEConfigError, match=r"ude\.depth == 0"):
        train_stack([a, e], None)  # type: ignore[arg-type]
    with pytest.raises(UDEConfigError, match=r"final_eval must be 'own' or 'batched', but got 'best'"):
        train_stack([a], None, final_eval="best")  # type: ignore[arg-type]


def test_patience_waits_while_the_training_fit_improves_alone_and_stacked(short_project: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """``train.patience_fit_gain``: an evaluation that lowers the training RMSE by that share counts
    as progress, so training goes on where validation alone would have stopped it; the best
    checkpoint is still the one that validates best; a stack stops each model where it alone stops."""
    monkeypatch.chdir(short_project)
    over = ["train.epochs=24", "train.patience=1", *TRIALS[1], "train.lr=0.05"]
    plain = train(_cfg(short_project, *over), load_problem(_cfg(short_project, *over)))
    cfg = _cfg(short_project, *over, "train.patience_fit_gain=1e-6")
    waits = train(cfg, load_problem(cfg))
    seen = [r["epoch"] for r in plain.history]
    assert seen[-1] < 24, f"validation alone should stop this training early: {plain.history}"
    longer = [r["epoch"] for r in waits.history]
    assert longer[: len(seen)] == seen and len(longer) > len(seen), (seen, longer)
    # where validation alone stopped, the training fit had improved: that is why it went on
    stop = waits.history[len(seen) - 1]
    assert stop["val.rmse"] > min(r["val.rmse"] for r in waits.history[: len(seen) - 1])
    assert stop["train.rmse"] < min(r["train.rmse"] for r in waits.history[: len(seen) - 1])
    assert waits.val_rmse == pytest.approx(min(r["val.rmse"] for r in waits.history), rel=1e-6)
    assert waits.val_rmse <= plain.val_rmse * (1 + 1e-6)
    stacked = train_stack([cfg, _cfg(short_project, *over, "train.patience_fit_gain=1e-6", "seed=5")],
                          load_problem(cfg))
    assert [r["epoch"] for r in stacked[0].history] == longer
    with pytest.raises(ConfigError, match=r"train.patience_fit_gain must be a number in \[0, 0.5\], but got 0.9"):
        _cfg(short_project, "train.patience_fit_gain=0.9")  # refused when the configuration is composed
    with pytest.raises(ConfigError, match=r"mask.retrain_epochs must be a whole number ≥ 1, but got 0"):
        _cfg(short_project, "mask.retrain_epochs=0")


def test_a_stack_over_the_memory_limit_trains_in_parts_that_fit(short_project: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """More models than ``train.memory_limit_gib`` allows at once: consecutive stacks that fit, each
    model reported under its own position; a model over the limit alone is refused, the others train."""
    from physmend.ude.stack.plan import setup
    from physmend.ude.timescale import GIB, TimeSettingError, budget_parts, steps_bytes

    monkeypatch.chdir(short_project)
    problem = load_problem(_cfg(short_project, *TRIALS[0]))
    settings = [resolve_settings(training_settings(_cfg(short_project, *t)), problem) for t in TRIALS]
    _, plan = setup(problem, settings[0])

    def need(*models: int) -> float:  # GiB, as the budget check estimates it
        return steps_bytes(int(plan.steps), int(plan.starts.shape[0]), problem, [settings[i] for i in models]) / GIB

    assert need(0, 1) < need(0, 1, 2) and need(1) < need(2) < need(0, 1)  # the widths and depths of TRIALS
    cases = {
        (need(0, 1) + need(0, 1, 2)) / 2: ([[0, 1], [2]], {0, 1, 2}),  # two fit together, the third alone
        (need(1) + need(2)) / 2: ([[0], [1], [2]], {0, 1}),  # each alone; the third over the limit even alone
    }
    for limit, (parts, trained) in cases.items():
        cfgs = [_cfg(short_project, *t, f"train.memory_limit_gib={limit!r}") for t in TRIALS]
        assert budget_parts(plan, problem, [resolve_settings(training_settings(c), problem) for c in cfgs]) == parts
        seen: set[tuple[int, int]] = set()
        results = train_stack(cfgs, problem, report=lambda i, epoch, row: seen.add((i, epoch)))
        assert seen == {(i, e) for i in sorted(trained) for e in (0, 2, 4)}
        for i, result in enumerate(results):
            if i in trained:
                assert isinstance(result, TrainResult), result
                assert result.hybrid.spec.widths == [int(cfgs[i].ude.width)] * int(cfgs[i].ude.depth)
            else:
                assert isinstance(result, TimeSettingError)
                assert f"more than train.memory_limit_gib={limit:g}" in str(result) and "x 1 model(s)" in str(result)
