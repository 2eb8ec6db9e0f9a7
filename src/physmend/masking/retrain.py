"""Retraining the candidate equation sets: side by side (:mod:`physmend.masking.parallel`), a
retraining stuck at its warm start trained again for longer, and the kept network's held-out
metrics added for the report."""

from __future__ import annotations

import dataclasses
from typing import Any

from omegaconf import OmegaConf

from physmend.settings import MaskSettings, TrainSettings


def stuck_at_warm_start(result: Any) -> bool:
    """Whether a retraining's best checkpoint is its warm start (epoch 0): its training never
    validated better than the derivative-matching fit it started from."""
    if isinstance(result, BaseException) or not getattr(result, "history", None):
        return False
    history = result.history
    return len(history) > 1 and history[0]["epoch"] == 0 and min(history, key=lambda r: r["val.rmse"]) is history[0]


def longer_settings(work: Any, mc: Any) -> list[str]:
    """Overrides (dotlist) for training again a retraining stuck at its warm start
    (:func:`stuck_at_warm_start`): ``train.epochs`` × ``mask.retrain_epochs`` with as many L-BFGS
    polish iterations as before, and ``train.patience_fit_gain`` = ``mask.retrain_fit_gain``.

    A network that leaves a good warm start often fits the validation record worse for a while
    before it fits everything better; patience that counted validation alone stopped it there, and
    the cosine schedule had no time left. The retrained network is what every later stage reads
    and what must carry over to held-out conditions; a sweep's trials only need to be ranked."""
    mc, tc = MaskSettings.build(mc), TrainSettings.build(work.train)
    factor, gain = mc.retrain_epochs, mc.retrain_fit_gain
    return [f"train.epochs={tc.epochs * factor}", f"train.patience_fit_gain={gain!r}",
            f"train.polish={tc.polish / factor!r}"]


def retrain_sets(work: Any, problem: Any, todo: list[list[str]], mc: Any, train: Any) -> tuple[list[Any], list[int]]:
    """Each set of ``todo`` retrained (side by side); those stuck at their warm start trained again
    with :func:`longer_settings`, the longer run kept where it validates better. Returns the results
    and the positions trained again."""
    from physmend.masking.parallel import retrain_all, workers

    mc = MaskSettings.build(mc)
    n = workers(mc.workers)
    done = list(retrain_all(work, problem, todo, train, n))
    again = [i for i, r in enumerate(done) if stuck_at_warm_start(r)] if mc.retrain_epochs > 1 else []
    if again:
        longer = OmegaConf.merge(work, OmegaConf.from_dotlist(longer_settings(work, mc)))
        for i, r in zip(again, retrain_all(longer, problem, [todo[i] for i in again], train, n)):
            if not isinstance(r, BaseException) and r.val_rmse < done[i].val_rmse:
                done[i], r = r, done[i]
            close_figures(r)  # the run not kept: its fit figures are never shown
    return done, again


def close_figures(result: Any) -> None:
    """Close the matplotlib figures of a training result that is not kept (pyplot holds them)."""
    import matplotlib.pyplot as plt

    for fig in (getattr(result, "figures", None) or {}).values():
        plt.close(fig)


def with_held_out(result: Any, problem: Any, work: Any) -> Any:
    """``result`` (a :class:`physmend.ude.TrainResult` trained without the test experiments of
    ``problem``) with the test experiments' metrics (``test.*``, ``rmse.<test experiment>.*``) added
    from one whole-trajectory simulation — report only; unchanged where ``problem`` has none or
    the simulation leaves the finite range."""
    from physmend.ude import TrainingDiverged, evaluate

    test = {str(e.id) for e in problem.experiments if e.role == "test"}
    if not test or result.hybrid is None:
        return result
    try:
        metrics = evaluate(result.hybrid, problem, work)
    except TrainingDiverged:
        return result
    held = {k: v for k, v in metrics.items()
            if k.startswith("test.") or any(k.startswith(f"rmse.{e}.") for e in test)}
    return dataclasses.replace(result, metrics={**result.metrics, **held})
