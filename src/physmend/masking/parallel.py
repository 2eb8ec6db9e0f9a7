"""The mask's retrainings — one network per candidate equation set — side by side in forked processes.

Each retraining is an independent ``train()`` of the same problem (one torch thread, seeded as the
configuration says), so ``mask.workers`` processes run them at once with the same results as one
after another. Children are forked (the problem, with its compiled functions, is inherited, never
pickled); each sends back what the mask needs: metrics, history, artifacts, figures and the
network's weights, from which the parent rebuilds the :class:`~physmend.ude.hybrid.HybridModel`.
Where ``fork`` is not available the retrainings run one after another.
"""

from __future__ import annotations

import multiprocessing
import pickle
from collections.abc import Callable, Sequence
from typing import Any

from omegaconf import OmegaConf

from physmend.cpus import usable_cpus
from physmend.settings import TrainSettings

#: (configuration, problem, trainer, equation sets) of the retrainings a forked child runs
_JOB: tuple[Any, Any, Callable[..., Any], list[list[str]]] | None = None


def workers(setting: Any) -> int:
    """``mask.workers``: a whole number ≥ 1, or ``auto`` (the CPUs this process may use)."""
    if str(setting) == "auto":
        return usable_cpus()
    return max(1, int(setting))


def retrain(work: Any, problem: Any, names: Sequence[str], train: Callable[..., Any], position: int = 0) -> Any:
    """A network that corrects only ``names``, trained; its :class:`TrainingDiverged` if it diverged."""
    from tqdm import tqdm

    from physmend.ude import TrainingDiverged

    cfg = OmegaConf.create(OmegaConf.to_container(work))
    cfg.ude.corrected = [n for n in problem.model.state_names if n in names]
    bar = tqdm(total=TrainSettings.build(cfg.train).epochs, desc=f"mask: retraining {', '.join(cfg.ude.corrected)}", unit="epoch",
               dynamic_ncols=True, position=position)

    def report(epoch: int, row: dict[str, float]) -> None:
        bar.update(max(0, min(int(epoch), bar.total) - bar.n))  # polish iterations past the epochs: the bar is full
        bar.set_postfix_str(f"val.rmse {row.get('val.rmse', float('nan')):.4g}")

    try:
        return train(cfg, problem, report=report)
    except TrainingDiverged as exc:
        return exc
    finally:
        bar.close()


def _packed(i: int) -> bytes:
    """In a forked child: retraining ``i`` of :data:`_JOB`, pickled without its model object."""
    assert _JOB is not None
    work, problem, train, sets = _JOB
    import torch

    torch.set_num_threads(1)  # one thread per retraining side by side (the loops' threaded twins are not forked into)
    result = retrain(work, problem, sets[i], train, position=i)
    if isinstance(result, BaseException):
        return pickle.dumps(result)
    hybrid = result.hybrid
    state = {"spec": hybrid.spec, "weights": hybrid.state_dict(), "estimates": dict(hybrid.initial_estimates)}
    try:
        figures = pickle.dumps(result.figures)
    except Exception:  # noqa: BLE001 - a figure that does not pickle: the run goes without the fit figures
        figures = pickle.dumps({})
    return pickle.dumps((result.val_rmse, result.metrics, result.history, result.artifacts, figures, state))


def _unpacked(blob: bytes, problem: Any) -> Any:
    from physmend.ude import TrainResult
    from physmend.ude.hybrid import HybridModel

    value = pickle.loads(blob)  # noqa: S301 - bytes from this process's own forked child, never from a store
    if isinstance(value, BaseException):
        return value
    val_rmse, metrics, history, artifacts, figures, state = value
    hybrid = HybridModel(problem.compiled, state["spec"], problem.dtype)
    hybrid.load_state_dict(state["weights"])
    hybrid.initial_estimates = state["estimates"]
    return TrainResult(val_rmse=val_rmse, metrics=metrics, history=history, artifacts=artifacts,
                       figures=pickle.loads(figures), hybrid=hybrid)  # noqa: S301 - as above


def retrain_all(work: Any, problem: Any, sets: list[list[str]], train: Callable[..., Any], n_workers: int) -> list[Any]:
    """One retraining per equation set of ``sets``, in order; ``n_workers`` at a time in forked processes
    (one after another when training runs on a GPU: CUDA does not survive a fork, and the GPU is one)."""
    global _JOB
    if (n_workers <= 1 or len(sets) <= 1 or "fork" not in multiprocessing.get_all_start_methods()
            or problem.device.type != "cpu"):
        return [retrain(work, problem, names, train) for names in sets]
    _JOB = (work, problem, train, sets)
    try:
        with multiprocessing.get_context("fork").Pool(min(n_workers, len(sets))) as pool:
            pending = pool.map_async(_packed, range(len(sets)), chunksize=1)
            # the loop this process runs next on all its threads (the kept network's trajectories),
            # compiled while the children train (seconds once per installation; then numba's cache)
            from physmend.ude.fixed_step import warm_shared

            warm_shared(problem.dtype)
            blobs = pending.get()
    finally:
        _JOB = None
    return [_unpacked(b, problem) for b in blobs]
