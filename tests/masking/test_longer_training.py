"""The mask's second, longer training of a retraining stuck at its warm start: when it happens,
what it changes, and the settings' checks."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from physmend.config import ConfigError, compose
from physmend.problem import load_problem
from physmend.masking.retrain import longer_settings, retrain_sets, stuck_at_warm_start
from physmend.ude import train

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=10",
        "train.eval_every=5", "train.patience=1", "train.polish=0.4", "ude.width=8", "ude.depth=1",
        "simulate=explicit", "simulate.rtol=1e-5", "simulate.atol=1e-6"]


def _cfg(project: Path, *overrides: str):  # noqa: ANN202
    return compose([*TINY, *overrides], user_config_dir=project / "my_conf")


def test_longer_settings_keep_the_polish_and_the_checks_refuse_bad_values(user_project: Path) -> None:
    cfg = _cfg(user_project)
    tc = OmegaConf.merge(cfg, OmegaConf.from_dotlist(longer_settings(cfg, cfg.mask))).train
    assert (tc.epochs, tc.patience_fit_gain) == (30, 0.01)  # mask.retrain_epochs 3, mask.retrain_fit_gain 0.01
    assert round(tc.polish * tc.epochs) == round(0.4 * 10)  # as many L-BFGS iterations as the first training
    with pytest.raises(ConfigError, match=r"mask.retrain_fit_gain must be a number in \[0, 0.5\], but got 2"):
        _cfg(user_project, "mask.retrain_fit_gain=2")
    with pytest.raises(ConfigError, match=r"mask.retrain_epochs must be a whole number ≥ 1, but got 0"):
        _cfg(user_project, "mask.retrain_epochs=0")


def test_a_retraining_stuck_at_its_warm_start_is_trained_again_longer(user_project: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    calls: list[tuple[int, float]] = []

    def observed(cfg, problem, **kw):  # noqa: ANN001, ANN202 - the real trainer, its settings recorded
        calls.append((int(cfg.train.epochs), float(cfg.train.patience_fit_gain)))
        return train(cfg, problem, **kw)

    # a learning rate far too large and no polish: training only makes the warm start worse
    cfg = _cfg(user_project, "train.lr=10", "train.polish=0", "mask.workers=1")
    problem = load_problem(cfg)
    done, again = retrain_sets(cfg, problem, [["cart.v"]], cfg.mask, observed)
    assert again == [0] and calls == [(10, 0.0), (30, 0.01)], calls
    first = train(cfg, problem)
    assert stuck_at_warm_start(first) and done[0].val_rmse <= first.val_rmse
    # mask.retrain_epochs=1: never trained again
    calls.clear()
    off = _cfg(user_project, "train.lr=10", "train.polish=0", "mask.workers=1", "mask.retrain_epochs=1")
    done, again = retrain_sets(off, problem, [["cart.v"]], off.mask, observed)
    assert again == [] and calls == [(10, 0.0)] and done[0].val_rmse == pytest.approx(first.val_rmse, rel=1e-9)
    # a training that validated better than its warm start is not trained again
    calls.clear()
    good = _cfg(user_project, "train.lr=0.05", "train.polish=0", "mask.workers=1")
    done, again = retrain_sets(good, problem, [["cart.v"]], good.mask, observed)
    assert again == [] and calls == [(10, 0.0)] and not stuck_at_warm_start(done[0])
