"""``reference(shared_clock=False)``: a model judged against its records is simulated with each
record's steps ending on its own times, not on every record's (the cargo box's three records are
sampled at different times: 717 each, 1,946 together)."""

from __future__ import annotations

import pytest
import torch

import physmend.simulate.clocks as clocks
import physmend.simulate.rodas as rodas
from physmend.config import compose
from physmend.problem import load_problem
from physmend.ude import reference


def test_each_record_on_its_own_clock_takes_fewer_steps_and_agrees_at_its_times(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = compose([])
    problem = load_problem(cfg)
    steps = [0]

    def counted(step):  # noqa: ANN001, ANN202 - the solver's own step, counted
        def run(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            steps[0] += 1
            return step(*args, **kwargs)
        return run

    monkeypatch.setattr(rodas, "rodas_step", counted(rodas.rodas_step))
    monkeypatch.setattr(clocks, "rodas_step", counted(clocks.rodas_step))
    shared = reference(problem, cfg)
    on_shared, steps[0] = steps[0], 0
    own = reference(problem, cfg, shared_clock=False)
    assert 0 < steps[0] < 0.6 * on_shared  # (the union of the records' times: 1,946 rows)
    model, batch = problem.compiled, shared.batch
    seen = torch.isfinite(batch.obs)  # each record's own times
    y_shared = model.outputs(shared.states, shared.inputs, batch.params[None])[seen]
    y_own = model.outputs(own.states, own.inputs, batch.params[None])[seen]
    sim = cfg.simulate
    assert torch.allclose(y_own, y_shared, rtol=10 * float(sim.rtol), atol=10 * float(sim.atol))
    assert not torch.equal(y_own, y_shared)  # two solves, not one
