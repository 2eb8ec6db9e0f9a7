"""The training solve's precomputed drives (physics B·x + c, the network's first layer on inputs and
parameters, normalisation folded in) give the same trajectories and gradients as the plain
right-hand side: for one model and for a stack, with subsets of states, inputs, parameters and
corrected equations, both correction units and an estimated parameter."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude import fixed_step
from physmend.ude.drive import drivable, hybrid_drive
from physmend.ude.hybrid import HybridModel
from physmend.ude.shooting import BOX_MARGIN, initial_segments, plan_shooting, rk4_segments
from physmend.ude.spec import build_spec
from physmend.ude.timescale import resolve_times
from physmend.ude.reference import reference

BASE = ["model=oscillator", "data=oscillator", "train.step=0.1", "train.segment_length=5", "simulate=explicit"]
VARIANTS = [
    [],
    ["ude.units=state", "ude.activation=tanh", "ude.depth=1"],
    ["ude.inputs.states=[cart.v]", "ude.inputs.parameters=[cart.x0, spring.k]", "ude.corrected=[cart.v]"],
    ["ude.inputs.inputs=false", "ude.activation=gelu", "ude.depth=3", "ude.width=7"],
]


def _setup(project: Path, extra: list[str]):  # noqa: ANN202
    cfg = compose([*BASE, *extra], user_config_dir=project / "my_conf")
    problem = load_problem(cfg)
    ref = reference(problem, cfg)
    cfg = resolve_times(cfg, problem, ref)
    torch.manual_seed(0)
    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, ref), problem.dtype)
    with torch.no_grad():  # a trained-looking network: corrections of a visible size
        for prm in hybrid.net.parameters():
            prm.add_(0.3 * torch.randn_like(prm))
    plan = plan_shooting(problem, ref.batch, cfg)
    u0 = initial_segments(problem, ref, plan)
    return cfg, problem, ref, hybrid, plan, u0


@pytest.mark.parametrize("extra", VARIANTS, ids=["default", "state-units", "subsets", "no-inputs-deep"])
def test_the_drive_is_the_right_hand_side(user_project: Path, monkeypatch: pytest.MonkeyPatch, extra: list[str]) -> None:
    monkeypatch.chdir(user_project)
    _, problem, ref, hybrid, plan, u0 = _setup(user_project, extra)
    assert drivable(hybrid) and hybrid.spec.estimated == ["damper.c"]
    params_seg = ref.batch.params[plan.exp_index]
    box = hybrid.spec.box(BOX_MARGIN, problem.dtype)

    def grads(mode: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
        hybrid.zero_grad(set_to_none=True)
        p = hybrid.parameters_for(params_seg)
        if mode == "drive":
            rhs, drives = hybrid_drive(hybrid, p, plan.x_half)
            traj = rk4_segments(rhs, u0, plan, box, drives)
        elif mode == "drive, a matrix per experiment":  # as train() calls it
            rhs, drives = hybrid_drive(hybrid, hybrid.parameters_for(ref.batch.params), plan.x_half, plan.exp_index)
            traj = rk4_segments(rhs, u0, plan, box, drives)
        elif mode == "rhs, a matrix per experiment":
            traj = rk4_segments(hybrid.rhs(hybrid.parameters_for(ref.batch.params), plan.exp_index), u0, plan, box)
        else:
            traj = rk4_segments(hybrid.rhs(p), u0, plan, box)
        (traj.pow(2).sum() + traj[-1, :, 0].sum()).backward()
        return traj.detach(), [q.grad.clone() for q in hybrid.parameters()]

    assert len(set(plan.exp_index.tolist())) >= 2  # segments of several experiments
    slow_traj, slow_grads = grads("rhs")
    assert float((slow_traj - problem.compiled.bind(params_seg)(u0, plan.x_half[0])[None]).abs().max()) > 0
    for mode in ("drive", "drive, a matrix per experiment", "rhs, a matrix per experiment"):
        fast_traj, fast_grads = grads(mode)
        torch.testing.assert_close(fast_traj, slow_traj, rtol=1e-10, atol=1e-12)
        assert len(fast_grads) == len(slow_grads) >= 4
        for a, b in zip(fast_grads, slow_grads):
            assert float(b.abs().max()) > 0  # every network weight and the estimate get a gradient
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)


def test_the_stack_drive_is_the_stack_right_hand_side(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Three models of different depths and activations in one stack: the drive's solve equals the
    plain stacked right-hand side's, trajectories and gradients."""
    from physmend.settings import training_settings
    from physmend.ude.stack.members import prepare
    from physmend.ude.stack.solve import Stack

    monkeypatch.chdir(user_project)
    trials = [["seed=1", "ude.width=8", "ude.depth=1", "ude.activation=tanh"],
              ["seed=2", "ude.width=16", "ude.depth=2", "ude.activation=softplus"],
              ["seed=3", "ude.width=12", "ude.depth=3", "ude.activation=gelu"]]
    cfgs = [compose([*BASE, *t], user_config_dir=user_project / "my_conf") for t in trials]
    problem = load_problem(cfgs[0])
    ref = reference(problem, cfgs[0])
    cfgs = [resolve_times(c, problem, ref) for c in cfgs]
    plan = plan_shooting(problem, ref.batch, cfgs[0])
    stack = Stack([prepare(training_settings(c), problem, ref, plan, i, warm=False) for i, c in enumerate(cfgs)],
                  problem, ref, plan, cfgs[0])
    with torch.no_grad():
        for w in stack.net.weights:
            w.add_(0.3 * torch.randn_like(w))
    m, plan = stack.size, stack.plan_rows
    s, n = stack.seg0.shape[1:]
    p = stack._parameters_for(stack.params_seg, stack.est_raw, m)
    u0 = stack.seg0.reshape(m * s, n)

    def grads(fast: bool) -> tuple[torch.Tensor, list[torch.Tensor]]:
        for q, *_ in stack.params:
            q.grad = None
        drive = stack._drive(stack.net, m, p, plan.x_half) if fast else None
        if fast:
            assert drive is not None
            traj = rk4_segments(drive[0], u0, plan, stack.box, drive[1])
        else:
            traj = rk4_segments(stack._rhs(stack.net, m, p), u0, plan, stack.box)
        traj.pow(2).sum().backward(retain_graph=True)
        return traj.detach(), [q.grad.clone() for q, *_ in stack.params[:-1] if q.grad is not None]

    slow_traj, slow_grads = grads(False)
    fast_traj, fast_grads = grads(True)
    torch.testing.assert_close(fast_traj, slow_traj, rtol=1e-10, atol=1e-12)
    assert len(fast_grads) == len(slow_grads) == len(stack.params) - 1
    for a, b in zip(fast_grads, slow_grads):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)


RODAS = {"method": "rodas4", "rtol": 1e-4, "atol": 1e-4, "options": {}}


@pytest.mark.parametrize("extra", VARIANTS, ids=["default", "state-units", "subsets", "no-inputs-deep"])
def test_the_drive_table_is_the_right_hand_side(user_project: Path, monkeypatch: pytest.MonkeyPatch, extra: list[str]) -> None:
    """The whole-trajectory drive (its values at the input knots, interpolated) gives the plain
    right-hand side's derivative at any time, between knots too, for one state and for the copies of a
    finite-difference Jacobian; and a checkpoint's metrics are the plain solve's to rounding."""
    import physmend.ude.metrics as metrics
    from physmend.ude.drive import drive_table

    monkeypatch.chdir(user_project)
    monkeypatch.setattr(fixed_step, "LEVELS", 0)  # the adaptive solves compared (fixed steps: test_fixed_step.py)
    _, problem, ref, hybrid, _, _ = _setup(user_project, extra)
    batch = ref.batch
    p = hybrid.parameters_for(batch.params)
    plain = hybrid.rhs(p)
    f, table = drive_table(hybrid, p, batch.inputs)
    torch.manual_seed(1)
    t0, t1 = float(batch.t[0]), float(batch.t[-1])
    times = [batch.inputs.knots[3].expand(batch.size), t0 + (t1 - t0) * torch.rand(batch.size, dtype=batch.t.dtype)]
    for t in times:
        u = ref.states[5] + 0.1 * torch.randn_like(ref.states[5])
        torch.testing.assert_close(f(u, table.each(t)), plain(u, batch.inputs.each(t)), rtol=1e-10, atol=1e-12)
        copies = u[None] + 0.01 * torch.randn(4, *u.shape, dtype=u.dtype)
        torch.testing.assert_close(f(copies, table.each(t)), plain(copies, batch.inputs.each(t)), rtol=1e-10, atol=1e-12)
        scalar = t[0]
        torch.testing.assert_close(f(u, table(scalar)), plain(u, batch.inputs(scalar)), rtol=1e-10, atol=1e-12)

    fast = metrics.evaluate_with(hybrid, problem, RODAS)
    monkeypatch.setattr(metrics, "drivable", lambda h: False)
    slow = metrics.evaluate_with(hybrid, problem, RODAS)
    for key in ("val.rmse", "train.rmse"):
        assert fast[0][key] == pytest.approx(slow[0][key], rel=1e-7)
    torch.testing.assert_close(fast[1], slow[1], rtol=0, atol=1e-7 * float(slow[1].abs().max()), equal_nan=True)


def test_the_stack_drive_table_gives_the_stack_checkpoints(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stack's checkpoint evaluation through the drive table gives the plain stacked right-hand
    side's metrics to rounding, for every model (two activations, one shape)."""
    from physmend.settings import training_settings
    from physmend.ude.stack.members import prepare
    from physmend.ude.stack.solve import Stack

    monkeypatch.chdir(user_project)
    trials = [["seed=1", "ude.width=8", "ude.depth=2", "ude.activation=tanh"],
              ["seed=2", "ude.width=8", "ude.depth=2", "ude.activation=softplus"],
              ["seed=3", "ude.width=8", "ude.depth=2", "ude.activation=tanh"]]
    cfgs = [compose([*BASE, *t], user_config_dir=user_project / "my_conf") for t in trials]
    problem = load_problem(cfgs[0])
    ref = reference(problem, cfgs[0])
    cfgs = [resolve_times(c, problem, ref) for c in cfgs]
    plan = plan_shooting(problem, ref.batch, cfgs[0])
    stack = Stack([prepare(training_settings(c), problem, ref, plan, i, warm=False) for i, c in enumerate(cfgs)],
                  problem, ref, plan, cfgs[0])
    with torch.no_grad():
        for w in stack.net.weights:
            w.add_(0.3 * torch.randn_like(w))
    positions = list(range(stack.size))
    net = stack.net.select(torch.tensor(positions))
    p = stack._parameters_for(ref.batch.params, None if stack.est_raw is None else stack.est_raw.detach(), stack.size)
    assert stack._drive_table(net, stack.size, p, ref.batch.take(torch.arange(ref.batch.size).repeat(stack.size)).inputs) is not None
    monkeypatch.setattr(fixed_step, "LEVELS", 0)  # the adaptive solves compared (fixed steps: test_fixed_step.py)
    fast = stack.evaluate(positions, RODAS)
    monkeypatch.setattr(Stack, "_drive_table", lambda self, *a: None)
    slow = stack.evaluate(positions, RODAS)
    for a, b in zip(fast, slow):
        assert not isinstance(a, BaseException) and not isinstance(b, BaseException)
        for key in ("val.rmse", "train.rmse"):
            assert a[0][key] == pytest.approx(b[0][key], rel=1e-7)
        torch.testing.assert_close(a[1], b[1], rtol=0, atol=1e-7 * float(b[1].abs().nan_to_num().max()), equal_nan=True)


def test_a_drive_table_over_the_memory_bound_is_not_built(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The drive table costs ``n + h1`` columns per row where the inputs had ``m``: over
    ``TABLE_MAX_BYTES`` (a long record, a wide stack) the plain right-hand side solves, with the same
    metrics; never an allocation in proportion to record × models × width."""
    import physmend.ude.drive as drive
    import physmend.ude.metrics as metrics

    assert not drive.table_fits(16, 20_000, 2 + 64, torch.float64)  # a 16-model stack, 20,000 knots: 338 MB
    assert drive.table_fits(3, 600, 2 + 16, torch.float64)
    monkeypatch.chdir(user_project)
    monkeypatch.setattr(fixed_step, "LEVELS", 0)  # the adaptive solves compared
    _, problem, _, hybrid, _, _ = _setup(user_project, [])
    fast = metrics.evaluate_with(hybrid, problem, RODAS)
    monkeypatch.setattr(drive, "TABLE_MAX_BYTES", 0)

    def never(*args: object) -> None:
        raise AssertionError("a drive table over the bound was built")

    monkeypatch.setattr(metrics, "drive_table", never)
    slow = metrics.evaluate_with(hybrid, problem, RODAS)
    assert slow[0]["val.rmse"] == pytest.approx(fast[0]["val.rmse"], rel=1e-7)


def test_masked_variants_in_one_solve_get_their_own_evaluations(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The mask's variants (the network with only some corrections) simulated in one solve, where each
    record has its own clock, give each variant the metrics its own evaluation gives; a variant that
    diverges makes each variant be simulated alone, that one's outcome its TrainingDiverged."""
    import pandas as pd

    import physmend.ude.metrics as metrics
    from physmend.ude.metrics import checkpoint_problem, evaluate, evaluate_kept
    from physmend.ude.outcome import TrainingDiverged
    from physmend.ude.reference import clocked
    from physmend.simulate import make_batch

    monkeypatch.chdir(user_project)
    monkeypatch.setattr(fixed_step, "LEVELS", 0)  # the adaptive solve of the variants (fixed steps: test_fixed_step.py)
    path = user_project / "recordings" / "run2.csv"
    frame = pd.read_csv(path)
    frame.loc[frame.index[1:], "t_s"] += 0.05  # between run1's times (each counts from its start)
    frame.to_csv(path, index=False)
    _, problem, _, hybrid, _, _ = _setup(user_project, ["ude.corrected=[cart.x,cart.v]"])
    checked = checkpoint_problem(problem)
    assert clocked(RODAS, make_batch(checked.experiments, checked.compiled, checked.dtype))
    corrected = list(hybrid.spec.corrected)
    keeps = [corrected, corrected[:1], corrected[1:], []]
    assert len(corrected) == 2
    solves: list[int] = []
    real = metrics.simulate_with
    monkeypatch.setattr(metrics, "simulate_with", lambda *a, **k: solves.append(a[1].size) or real(*a, **k))
    together = evaluate_kept(hybrid, checked, RODAS, keeps)
    assert solves == [len(keeps) * 2]  # one solve, every variant's two records
    assert torch.equal(hybrid.out_mask, torch.ones(2, dtype=hybrid.out_mask.dtype))
    vals = set()
    for keep, got in zip(keeps, together):
        hybrid.keep_only(keep)
        alone = evaluate(hybrid, checked, sim=RODAS)
        assert isinstance(got, dict) and set(got) == set(alone)
        for key, value in alone.items():
            assert got[key] == pytest.approx(value, rel=1e-8), (keep, key)
        vals.add(round(got["val.rmse"], 6))
    assert len(vals) == len(keeps)  # the variants differ: the masks reached the solve
    # a variant that leaves every range: the solve fails, and each variant is simulated alone
    hybrid.keep_only(corrected)
    with torch.no_grad():
        hybrid.net[-1].bias.fill_(1e6)
    outcomes = evaluate_kept(hybrid, checked, RODAS, [corrected, []])
    assert isinstance(outcomes[0], TrainingDiverged)
    hybrid.keep_only([])
    assert outcomes[1] == evaluate(hybrid, checked, sim=RODAS)
