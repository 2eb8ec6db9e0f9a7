"""The mask's retrainings side by side in forked processes give what one after another gives."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem
from physmend.masking.parallel import retrain_all, workers
from physmend.ude import TrainResult, train

TINY = ["model=oscillator", "data=oscillator", "train.step=0.1", "train.segment_length=5.0", "train.epochs=4",
        "train.eval_every=2", "simulate.method=bosh3", "simulate.rtol=1e-4", "simulate.atol=1e-5", "ude.width=8"]


def test_parallel_retrainings_equal_sequential_ones(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = compose(TINY, user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    sets = [["cart.v"], ["cart.x", "cart.v"]]
    one = retrain_all(cfg, problem, sets, train, 1)
    two = retrain_all(cfg, problem, sets, train, 2)
    assert workers("auto") >= 1 and workers(3) == 3
    for a, b, names in zip(one, two, sets):
        assert isinstance(a, TrainResult) and isinstance(b, TrainResult), (a, b)
        assert b.hybrid.spec.corrected == a.hybrid.spec.corrected == [n for n in ("cart.x", "cart.v") if n in names]
        assert b.val_rmse == a.val_rmse and repr(b.history) == repr(a.history)  # (NaN loss at the warm start)
        for (k, va), (_, vb) in zip(a.hybrid.state_dict().items(), b.hybrid.state_dict().items()):
            assert torch.equal(va, vb), k
        assert set(b.artifacts) == set(a.artifacts) and set(b.figures) == set(a.figures)
