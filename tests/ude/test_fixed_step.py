"""Whole-trajectory solves by fixed-step RK4 with step doubling (:mod:`physmend.ude.fixed_step`):
within the tolerance asked of a tight adaptive solve for every network shape the drive form takes,
declined (None) where the grids cannot agree or the states leave their limits, the Hermite values
between grid points, and a whole evaluation (:func:`evaluate_with`) that gives the adaptive
solve's metrics."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from physmend.simulate import make_batch
from physmend.ude import fixed_step
from physmend.ude.drive import drive_table
from physmend.ude.fixed_step import hybrid_form, rk4_states
from physmend.ude.metrics import evaluate_with, row_stops
from physmend.ude.reference import simulate_with, with_stops

from tests.ude.test_drive import VARIANTS, _setup

SIM = {"method": "rodas4", "rtol": 1e-6, "atol": 1e-6, "options": {}}


def _tight(hybrid, problem, batch):  # noqa: ANN001, ANN202
    """The adaptive solve of the drive form at tolerances far below the ones asked here."""
    p = hybrid.parameters_for(batch.params)
    rhs, table = drive_table(hybrid, p, batch.inputs)
    sim = {**SIM, "rtol": 1e-10, "atol": 1e-10}
    return simulate_with(rhs, dataclasses.replace(batch, inputs=table), batch.u0, with_stops(sim, batch))


@pytest.mark.parametrize("extra", VARIANTS, ids=["default", "state-units", "subsets", "no-inputs-deep"])
def test_within_the_tolerance_asked(user_project: Path, monkeypatch: pytest.MonkeyPatch, extra: list[str]) -> None:
    monkeypatch.chdir(user_project)
    _, problem, ref, hybrid, _, _ = _setup(user_project, extra)
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with torch.no_grad():
        exact = _tight(hybrid, problem, batch)
        form = hybrid_form(hybrid, hybrid.parameters_for(batch.params), batch.inputs)
        assert form is not None
        kept = fixed_step.STATS["kept"]
        states = rk4_states(form, batch.u0, batch.t, row_stops(batch, SIM), SIM["rtol"], SIM["atol"])
    assert states is not None and fixed_step.STATS["kept"] == kept + 1
    assert states.shape == exact.shape
    err = ((states - exact).abs() / (SIM["atol"] + SIM["rtol"] * exact.abs())).max()
    assert err <= 1.0, f"fixed-step states off by {float(err):.3g} tolerances"
    assert float((states - exact).abs().max()) > 0  # a solve of its own, not the adaptive one's values


def test_between_grid_points_and_declined(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    _, problem, ref, hybrid, _, _ = _setup(user_project, [])
    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    with torch.no_grad():
        exact = _tight(hybrid, problem, batch)
        p = hybrid.parameters_for(batch.params)
        form = hybrid_form(hybrid, p, batch.inputs)
        # values half-way between the records' times: the Hermite interpolant of the steps that span
        # them, against a solve whose grid holds them
        mid = 0.5 * (batch.t[:-1] + batch.t[1:])
        both = torch.sort(torch.cat([batch.t, mid])).values
        stops = row_stops(batch, SIM)
        states = rk4_states(form, batch.u0, both, stops, SIM["rtol"], SIM["atol"])
        on_grid = rk4_states(form, batch.u0, both, [both] * batch.size, SIM["rtol"], SIM["atol"])
        assert states is not None and on_grid is not None
        at_times = torch.isin(both, batch.t)
        assert float((states[at_times] - exact).abs().max()) < 1e-5
        assert float((states[~at_times] - on_grid[~at_times]).abs().max()) < 1e-5
        sparse = [batch.t[::3]] * batch.size  # steps across the inputs' kinks: second order there
        # tolerances no four grids can meet: left to the adaptive solve
        declined = fixed_step.STATS["declined"]
        assert rk4_states(form, batch.u0, batch.t, sparse, 1e-12, 1e-12) is None
        assert fixed_step.STATS["declined"] == declined + 1
        # a state past its limits: the adaptive solve reports it
        n = batch.u0.shape[-1]
        narrow = (exact.amin((0, 1)) + 0.1 * (exact.amax((0, 1)) - exact.amin((0, 1))), torch.full((n,), torch.inf))
        assert rk4_states(form, batch.u0, batch.t, None, 1e-6, 1e-6, narrow) is None


def test_evaluation_gives_the_adaptive_solves_metrics(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    _, problem, ref, hybrid, _, _ = _setup(user_project, [])
    kept = fixed_step.STATS["kept"]
    fast, y_fast, _ = evaluate_with(hybrid, problem, SIM)
    assert fixed_step.STATS["kept"] > kept
    monkeypatch.setattr(fixed_step, "LEVELS", 0)  # no grid: every solve is the adaptive one
    slow, y_slow, _ = evaluate_with(hybrid, problem, SIM)
    assert fast.keys() == slow.keys()
    for key in fast:
        assert fast[key] == pytest.approx(slow[key], rel=1e-4, abs=1e-6), key
    finite = torch.isfinite(y_slow)
    assert torch.equal(finite, torch.isfinite(y_fast))
    assert float((y_fast[finite] - y_slow[finite]).abs().max()) < 1e-4


def test_masked_variants_in_one_fixed_step_solve(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The mask's variants in one solve (a row mask each) by fixed steps: each variant's metrics are
    its own evaluation's and the adaptive solve's, to the tolerance asked."""
    import pandas as pd

    from physmend.ude.metrics import checkpoint_problem, evaluate, evaluate_kept

    monkeypatch.chdir(user_project)
    path = user_project / "recordings" / "run2.csv"
    frame = pd.read_csv(path)
    frame.loc[frame.index[1:], "t_s"] += 0.05  # between run1's times: a clock per record
    frame.to_csv(path, index=False)
    _, problem, _, hybrid, _, _ = _setup(user_project, ["ude.corrected=[cart.x,cart.v]"])
    checked = checkpoint_problem(problem)
    corrected = list(hybrid.spec.corrected)
    keeps = [corrected, corrected[:1], corrected[1:], []]
    kept = fixed_step.STATS["kept"]
    together = evaluate_kept(hybrid, checked, SIM, keeps)
    assert fixed_step.STATS["kept"] == kept + 1  # one fixed-step solve for the four variants
    alone = []
    for keep in keeps:
        hybrid.keep_only(keep)
        alone.append(evaluate(hybrid, checked, sim=SIM))
    monkeypatch.setattr(fixed_step, "LEVELS", 0)
    adaptive = []
    for keep in keeps:
        hybrid.keep_only(keep)
        adaptive.append(evaluate(hybrid, checked, sim=SIM))
    assert len({round(m["val.rmse"], 6) for m in together}) == len(keeps)  # each variant its own
    for got, own, slow in zip(together, alone, adaptive):
        assert got["val.rmse"] == pytest.approx(own["val.rmse"], rel=1e-4)
        assert got["val.rmse"] == pytest.approx(slow["val.rmse"], rel=1e-4)
