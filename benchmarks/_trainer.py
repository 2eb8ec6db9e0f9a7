"""(b) physmend's own trainer, ``physmend.ude.train.train``, stopped at the target by its callback.

Default configuration except ``train.eval_every`` (finer stopping resolution, the same as the
baseline's) and ``train.patience`` (rescaled so that early stopping waits the same number of
epochs as with the defaults).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import torch
from torch.optim.optimizer import register_optimizer_step_post_hook
from omegaconf import OmegaConf

from _common import Target, TargetReached, TimeCapReached
from _flops import count_network_rows, epoch_flops, rhs_flops

COUNT_EPOCHS = 4  # extra epochs of the second untimed FLOP-counting run


def with_eval_every(cfg: Any, eval_every: int) -> Any:
    """A copy of ``cfg`` evaluating every ``eval_every`` epochs; patience rescaled to the same epochs."""
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    default_every, patience = int(cfg.train.eval_every), int(cfg.train.patience)
    out.train.eval_every = eval_every
    if patience > 0:
        out.train.patience = max(1, round(patience * default_every / eval_every))
    return out


def run(cfg: Any, problem: Any, target: Target, *, cap_s: float, eval_every: int, seed: int) -> dict[str, Any]:
    """Call ``train`` until the target, the cap (s) or its own end; wall times (s) from the call."""
    from physmend.ude.outcome import TrainingDiverged
    from physmend.ude.train import train

    cfg = with_eval_every(cfg, eval_every)
    cfg.seed = seed
    history: list[dict[str, float]] = []
    start = time.perf_counter()

    def report(epoch: int, row: dict[str, float]) -> None:
        now = time.perf_counter() - start
        history.append({"epoch": epoch, "wall_s": now, "val.rmse": float(row["val.rmse"]), "loss": float(row.get("loss", float("nan")))})
        if target.met(float(row["val.rmse"])):
            raise TargetReached
        if now > cap_s:
            raise TimeCapReached

    steps: list[float] = []  # perf_counter after each training step: the direct per-epoch timer

    def stepped(opt: Any, *_: Any) -> None:
        # train()'s optimiser is AdamW (the warm start's derivative matching uses Adam, the polish L-BFGS)
        if type(opt) is torch.optim.AdamW:
            steps.append(time.perf_counter())

    hook = register_optimizer_step_post_hook(stepped)
    status = "ended"  # train returned: epochs or patience ran out before the target
    try:
        train(cfg, problem, report=report)
    except TargetReached:
        status = "reached"
    except TimeCapReached:
        status = "capped"
    except TrainingDiverged as exc:
        status = f"failed: {str(exc)[:200]}"
    finally:
        hook.remove()
    wall = time.perf_counter() - start
    epochs = int(history[-1]["epoch"]) if history else 0
    return {
        "status": status,
        "wall_s": wall,
        "epochs": epochs,
        "evaluations": len(history),
        "s_per_epoch": wall / epochs if epochs else float("nan"),
        "final_val_rmse": history[-1]["val.rmse"] if history else float("nan"),
        "eval_every": int(cfg.train.eval_every),
        "patience": int(cfg.train.patience),
        "history": history,
        "step_s": step_seconds(steps),
    }


def step_seconds(steps: list[float]) -> float:
    """Training time per epoch (s), measured directly: the median time between consecutive AdamW
    steps (one step per epoch); an interval that holds a checkpoint evaluation is one of every
    ``train.eval_every``, so the median is the step itself."""
    gaps = [b - a for a, b in zip(steps, steps[1:])]
    return float(statistics.median(gaps)) if gaps else float("nan")


def eval_seconds(cfg: Any, problem: Any) -> float:
    """Wall time (s) of one checkpoint evaluation (whole trajectories of the training and validation
    experiments, as ``train`` checks them; test experiments are simulated once, at the end) of a
    freshly initialised hybrid."""
    from physmend.ude.hybrid import HybridModel
    from physmend.ude.spec import build_spec
    from physmend.ude.metrics import checkpoint_problem, evaluate
    from physmend.ude.reference import reference

    hybrid = HybridModel(problem.compiled, build_spec(cfg, problem, reference(problem, cfg)), problem.dtype)
    checked = checkpoint_problem(problem)
    t0 = time.perf_counter()
    evaluate(hybrid, checked, cfg)
    return time.perf_counter() - t0


def train_step_seconds(history: list[dict[str, float]], eval_s: float) -> float:
    """Training time per epoch (s) without evaluations, from the callback times: between the first
    and last callback, minus one evaluation per callback interval."""
    if len(history) < 2:
        return float("nan")
    first, last = history[0], history[-1]
    span = last["wall_s"] - first["wall_s"] - (len(history) - 1) * eval_s
    return max(span, 0.0) / (last["epoch"] - first["epoch"])


def count_flops(cfg: Any, problem: Any) -> dict[str, Any]:
    """Untimed passes: rows through the network per training epoch (hooked), then the FLOP estimate.

    Two short runs (``COUNT_EPOCHS`` epochs apart) separate the per-epoch rows from one-off work
    before the first epoch (e.g. a warm start), which is reported as ``setup_rows``.
    """
    from physmend.ude.spec import build_spec
    from physmend.ude.reference import reference

    spec = build_spec(cfg, problem, reference(problem, cfg))
    per_row = rhs_flops(spec, len(problem.compiled.state_names), len(problem.compiled.input_names))
    first = spec.widths[0] if spec.widths else len(spec.corrected)
    short, long = (_rows_of_run(cfg, problem, n, spec.n_inputs, first) for n in (2, 2 + COUNT_EPOCHS))
    rows = (long - short) / COUNT_EPOCHS
    setup = max(short - 2 * rows, 0.0)
    source = f"counted (grad-enabled rows through the network: runs of 2 and {2 + COUNT_EPOCHS} epochs)"
    if rows <= 0:  # the trainer bypasses nn.Linear (e.g. stacked weights): fall back to the plan
        rows, setup, source = shooting_rows(cfg, problem), float("nan"), "analytic (RK4: 4 x steps per segment x segments)"
    return {"rows_per_epoch": rows, "rows_source": source, "rhs_flops": per_row,
            "flops_per_epoch": epoch_flops(rows, per_row["total"]), "setup_rows": setup,
            "setup_flops": epoch_flops(setup, per_row["total"])}


def _rows_of_run(cfg: Any, problem: Any, epochs: int, n_inputs: int, first_width: int) -> float:
    """Rows sent through the network with gradients enabled during ``train`` for ``epochs`` epochs."""
    from physmend.ude.train import train
    from physmend.ude.warmstart import forget_warm_starts

    forget_warm_starts()  # each pass fits its own warm start (a stored one would hide its rows)
    short = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    short.train.epochs, short.train.eval_every, short.train.patience = epochs, epochs, 0
    with count_network_rows(n_inputs, first_width) as counted:
        train(short, problem)
        return float(counted())


def shooting_rows(cfg: Any, problem: Any) -> float:
    """RHS row evaluations of one multiple-shooting RK4 epoch: 4 stages x steps x segments."""
    from physmend.simulate import make_batch
    from physmend.ude.shooting import plan_shooting

    batch = make_batch(problem.experiments, problem.compiled, problem.dtype)
    plan = plan_shooting(problem, batch, cfg)
    return float(4 * plan.steps * plan.exp_index.shape[0])
