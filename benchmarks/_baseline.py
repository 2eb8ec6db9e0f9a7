"""(a) The plain torchdiffeq baseline, written the way a straightforward user would.

The same hybrid model as physmend's (``HybridModel`` from ``build_spec``, same network defaults and
jointly estimated parameters), but the right-hand side goes through the generic lambdified
``problem.compiled.rhs(u, x, p)`` plus the network corrections; one ``torchdiffeq.odeint``
(dopri5, rtol = atol = 1e-6) over the training portion of all training experiments at once,
loss = MSE of the outputs at the training observation times, backprop through the solver,
Adam (lr 0.01). Every ``eval_every`` epochs: physmend's whole-trajectory ``evaluate``.
"""

from __future__ import annotations

import time
from typing import Any

import torch

from _common import Target, TimeCapReached
from _flops import epoch_flops, rhs_flops

LR = 0.01
RTOL = ATOL = 1e-6


def training_window(problem: Any) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(batch, t, y, mask)`` of the training experiments: times ``t (T,)`` (s) up to the last
    training sample, measurements ``y (T, B, k)`` and ``mask`` of training samples (before split)."""
    from physmend.simulate import make_batch

    batch = make_batch(problem.by_role("train"), problem.compiled, problem.dtype)
    is_train = batch.t[:, None] < batch.split_time[None, :]  # (T, B)
    ok = torch.isfinite(batch.obs) & is_train[..., None]
    last = batch.t[ok.any(dim=(1, 2))].max()
    keep = batch.t <= last
    return batch, batch.t[keep], batch.obs[keep], ok[keep]


def make_rhs(problem: Any, hybrid: Any, batch: Any, p: torch.Tensor, clock: dict[str, float]) -> Any:
    """``f(t, u)`` = lambdified physics + corrections of the corrected equations; counts calls
    in ``clock["nfe"]`` and raises :class:`TimeCapReached` once ``clock["deadline"]`` passes."""
    compiled = problem.compiled
    idx = torch.tensor(hybrid.corrected_idx, dtype=torch.long)

    def f(t: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        clock["nfe"] += 1
        if time.perf_counter() > clock["deadline"]:
            raise TimeCapReached
        x = batch.inputs(t)
        du = compiled.rhs(u, x, p)
        return du.index_add(-1, idx, hybrid.corrections(u, x, p))

    return f


def run(cfg: Any, problem: Any, target: Target, *, cap_s: float, eval_every: int, seed: int) -> dict[str, Any]:
    """Train until the target or the cap; wall times (s) count from before the reference simulation."""
    import torchdiffeq

    from physmend.ude.hybrid import HybridModel
    from physmend.ude.outcome import TrainingDiverged
    from physmend.ude.spec import build_spec
    from physmend.ude.metrics import checkpoint_problem, evaluate
    from physmend.ude.reference import reference

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    start = time.perf_counter()
    clock = {"nfe": 0.0, "deadline": start + cap_s}
    spec = build_spec(cfg, problem, reference(problem, cfg))
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    batch, t, y_obs, mask = training_window(problem)
    opt = torch.optim.Adam(hybrid.parameters(), lr=LR)
    history: list[dict[str, float]] = []
    train_s = eval_s = 0.0
    nfe_total = 0.0
    epoch, status = 0, "capped"
    try:
        while True:
            epoch += 1
            t0, nfe0 = time.perf_counter(), clock["nfe"]
            opt.zero_grad()
            p = hybrid.parameters_for(batch.params)
            states = torchdiffeq.odeint(make_rhs(problem, hybrid, batch, p, clock), batch.u0, t,
                                        method="dopri5", rtol=RTOL, atol=ATOL)
            y = problem.compiled.outputs(states, batch.inputs.at(t), p[None])
            loss = (y - y_obs)[mask].pow(2).mean()
            if not torch.isfinite(loss):
                status = f"failed: non-finite loss at epoch {epoch}"
                break
            loss.backward()
            opt.step()
            train_s += time.perf_counter() - t0
            nfe_total += clock["nfe"] - nfe0
            if epoch % eval_every == 0:
                t1 = time.perf_counter()
                val = evaluate(hybrid, checkpoint_problem(problem), cfg)["val.rmse"]  # as physmend's checkpoints
                eval_s += time.perf_counter() - t1
                history.append({"epoch": epoch, "wall_s": time.perf_counter() - start, "val.rmse": val, "loss": float(loss.detach())})
                if target.met(val):
                    status = "reached"
                    break
            if time.perf_counter() > clock["deadline"]:
                break
    except TimeCapReached:
        epoch -= 1  # the interrupted epoch did not finish
    except (AssertionError, RuntimeError, TrainingDiverged) as exc:  # torchdiffeq: "underflow in dt"
        status = f"failed: {type(exc).__name__}: {str(exc)[:200]}"
        epoch -= 1
    wall = time.perf_counter() - start
    per_row = rhs_flops(spec, len(problem.compiled.state_names), len(problem.compiled.input_names))
    rows = nfe_total / max(epoch, 1) * batch.size
    return {
        "status": status,
        "wall_s": wall,
        "epochs": epoch,
        "evaluations": len(history),
        "train_s_per_epoch": train_s / epoch if epoch else float("nan"),
        "eval_s": eval_s / len(history) if history else float("nan"),
        "eval_total_s": eval_s,
        "s_per_epoch": wall / epoch if epoch else float("nan"),
        "nfe_per_epoch": nfe_total / epoch if epoch else float("nan"),
        "rows_per_epoch": rows if epoch else float("nan"),
        "rows_source": "counted (dopri5 RHS calls incl. rejected steps x experiments)",
        "rhs_flops": per_row,
        "flops_per_epoch": epoch_flops(rows, per_row["total"]) if epoch else float("nan"),
        "final_val_rmse": history[-1]["val.rmse"] if history else float("nan"),
        "history": history,
    }
