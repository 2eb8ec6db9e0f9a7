"""A model as written that diverges: training's reference stays within the data, the time step
comes from there, a plan too large is refused before it is built, and training fits in memory.
A model that does not diverge gets its reference bit for bit."""

from __future__ import annotations

import resource
import sys
import time
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the users' projects  # noqa: E402
from diverging_projects import write_project  # noqa: E402
from physmend.config import compose
from physmend.problem import load_problem
from physmend.simulate import SimulationError
from physmend.ude import reference
from physmend.ude.shooting import plan_shooting
from physmend.ude.timescale import TimeSettingError, plan_bytes, resolve_times

GIB = 1024.0**3


def _problem(root: Path, kind: str, *extra: str):  # noqa: ANN202
    conf, name = write_project(root, kind)
    cfg = compose([f"model={name}", f"data={name}", *extra], user_config_dir=conf)
    return cfg, load_problem(cfg)


def _peak_rss() -> float:
    """This process's peak resident memory so far (bytes; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0


def test_growth_without_bound_is_found_and_the_reference_stays_within_the_data(tmp_path: Path) -> None:
    cfg, problem = _problem(tmp_path, "growth")
    plain = reference(problem, cfg)
    assert float(plain.states[..., 0].abs().max()) > 1e7  # exponential growth: 1e8 over the record
    ref = reference(problem, cfg, bounded=True)
    first = ref.divergence[0]
    assert first.name == "colony.x" and not first.blows_up
    assert 5.0 < first.time < 15.0  # days: exp(0.6 t) passes 3 ranges beyond the records' ~100 near t = 9
    assert {d.experiment for d in ref.divergence} == {"e1", "e2", "e3"}
    assert first.peak > 1e7 and "t = " in first.describe("d") and " d " in first.describe("d")
    assert float(ref.states[..., 0].abs().max()) <= first.box_high
    assert bool(torch.isfinite(ref.derivs).all())
    # the time step comes from the Jacobian along the bounded reference: half a sampling interval
    # (along the model as written the oxygen uptake q·x at x = 1e8 asks for a step of ~2e-6 d)
    assert float(resolve_times(cfg, problem, plain).train.step) < 1e-4
    work = resolve_times(cfg, problem, ref)
    assert float(work.train.step) == pytest.approx(0.125)
    plan = plan_shooting(problem, ref.batch, work)
    assert plan_bytes(plan, problem, [work]) < 0.05 * GIB


def test_a_plan_too_large_is_refused_in_one_line_before_it_is_built(tmp_path: Path) -> None:
    cfg, problem = _problem(tmp_path, "growth", "train.step=1e-7")
    ref = reference(problem, cfg, bounded=True)
    before, start = _peak_rss(), time.perf_counter()
    with pytest.raises(TimeSettingError) as info:
        plan_shooting(problem, ref.batch, resolve_times(cfg, problem, ref))
    assert time.perf_counter() - start < 5.0
    assert _peak_rss() - before < 0.2 * GIB  # its grid ((2·7.5e7 + 1) × 4 half steps) was never allocated
    msg = str(info.value)
    assert "\n" not in msg and "GiB" in msg and "train.memory_limit_gib=2" in msg and "train.step" in msg


def test_a_finite_time_blow_up_is_found_not_raised(tmp_path: Path) -> None:
    cfg, problem = _problem(tmp_path, "blowup")
    with pytest.raises(SimulationError):
        reference(problem, cfg)  # as before: the plain reference of a model that blows up fails
    ref = reference(problem, cfg, bounded=True)
    assert bool(torch.isfinite(ref.states).all())
    by_exp = {d.experiment: d for d in ref.divergence}
    assert set(by_exp) == {"e1", "e2", "e3"} and all(d.blows_up for d in ref.divergence)
    # dx/dt = a·x² from x0 blows up at 1/(a·x0): 2 tu for e1 (x0 = 1), 1.33 for e2 (1.5), 2.5 for e3 (0.8)
    for exp, x0 in (("e1", 1.0), ("e2", 1.5), ("e3", 0.8)):
        assert 0.8 / (0.5 * x0) < by_exp[exp].time <= 1.0 / (0.5 * x0) + 0.1, (exp, by_exp[exp].time)
    assert float(ref.states.abs().max()) <= ref.divergence[0].box_high


def test_a_model_that_does_not_diverge_gets_its_reference_bit_for_bit(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    plain, bounded = reference(problem, cfg), reference(problem, cfg, bounded=True)
    assert bounded.divergence == []
    for a, b in ((plain.states, bounded.states), (plain.derivs, bounded.derivs), (plain.observed, bounded.observed)):
        assert torch.equal(a, b)


def test_training_on_a_diverging_model_stays_within_its_memory_budget(tmp_path: Path) -> None:
    from physmend.ude.stack import train_stack

    cfg, problem = _problem(tmp_path, "growth", "train.epochs=4", "train.eval_every=2", "train.polish=0",
                            "train.restarts=0", "ude.width=8", "ude.depth=1")
    before, start = _peak_rss(), time.perf_counter()
    [result] = train_stack([cfg], problem, figures=False)
    assert not isinstance(result, BaseException), result
    assert time.perf_counter() - start < 60.0
    assert _peak_rss() - before < 1.0 * GIB
    assert result.val_rmse < 1e3  # the model as written misses by 1e7 on validation; trained, it is near the data
