"""The ``sweep.*`` options, checked on construction; the sampler and the pruner they make; the
searched keys that shape a stacked solve.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from physmend.config import ConfigError
from physmend.sweep.space import SearchSpace

if TYPE_CHECKING:
    import optuna

    from physmend.sweep.budget import Budget


SAMPLERS = ("tpe", "random")

PRUNERS = ("median", "halving", "none")



@dataclass(frozen=True)
class Settings:
    """``cfg.sweep``, checked on construction.

    ``restarts``: trainings of a diverged trial restarted before it fails (:mod:`physmend.sweep.restart`).
    ``budget`` (s of wall time, None: none) and ``max_trials``: the study has ``n_trials`` trials at
    least and as many more as the budget allows, ``max_trials`` at most (:mod:`physmend.sweep.budget`).
    """

    space: str
    n_trials: int
    study_name: str | None
    sampler: str
    n_startup_trials: int
    pruner: str
    pruner_startup_trials: int
    pruner_warmup_epochs: int
    pruner_min_epochs: int
    seed: int
    timeout: float | None
    heartbeat_interval: float
    stale_after: float
    max_failures_in_a_row: int
    progress: bool
    group: int = 1
    figures: bool = True
    workers: int = 1
    group_shapes: bool = True
    restarts: int = 2
    budget: float | None = None
    max_trials: int | None = None

    @property
    def budgeted(self) -> "Budget | None":
        """The sweep's :class:`~physmend.sweep.budget.Budget` (``sweep.budget``), or None: ``n_trials`` trials."""
        from physmend.sweep.budget import Budget

        if self.budget is None:
            return None
        low = max(1, self.n_trials)
        return Budget(self.budget, low, max(low, self.max_trials or low))

    @classmethod
    def from_cfg(cls, sweep: Any) -> Settings:
        def number(key: str, cast: Callable[[Any], Any], minimum: float, *, optional: bool = False) -> Any:
            value = sweep.get(key)
            if value is None and optional:
                return None
            try:
                out = cast(value)
            except (TypeError, ValueError):
                raise ConfigError(f"sweep.{key} must be a number >= {minimum}, but got {value!r}") from None
            if not out >= minimum:
                raise ConfigError(f"sweep.{key} must be >= {minimum}, but got {value!r}")
            return out

        def flag(key: str, default: bool) -> bool:
            value = sweep.get(key, default)
            if not isinstance(value, bool):
                raise ConfigError(f"sweep.{key} must be true or false, but got {value!r}")
            return value

        sampler, pruner = str(sweep.get("sampler", "tpe")), str(sweep.get("pruner", "median"))
        if sampler not in SAMPLERS:
            raise ConfigError(f"sweep.sampler must be one of {list(SAMPLERS)}, but got {sampler!r}")
        if pruner not in PRUNERS:
            raise ConfigError(f"sweep.pruner must be one of {list(PRUNERS)}, but got {pruner!r}")
        name = sweep.get("study_name")
        budget = number("budget", float, 0, optional=True)
        if budget is not None and not (budget > 0 and math.isfinite(budget)):
            raise ConfigError(f"sweep.budget must be a finite number of seconds > 0 or null, but got {sweep.get('budget')!r}")
        max_trials = number("max_trials", int, 1, optional=True)  # below n_trials: n_trials (the least)
        return cls(
            space=str(sweep.get("space", "default")),
            n_trials=number("n_trials", int, 0),
            study_name=None if name in (None, "") else str(name),
            sampler=sampler,
            n_startup_trials=number("n_startup_trials", int, 0),
            pruner=pruner,
            pruner_startup_trials=number("pruner_startup_trials", int, 0),
            pruner_warmup_epochs=number("pruner_warmup_epochs", int, 0),
            pruner_min_epochs=number("pruner_min_epochs", int, 1) if sweep.get("pruner_min_epochs") is not None else 10,
            seed=number("seed", int, 0),
            timeout=number("timeout", float, 0, optional=True),
            heartbeat_interval=number("heartbeat_interval", float, 0.1),
            stale_after=number("stale_after", float, 1.0),
            max_failures_in_a_row=number("max_failures_in_a_row", int, 0),
            progress=bool(sweep.get("progress", True)),
            group=number("group", int, 1) if sweep.get("group") is not None else 1,
            figures=bool(sweep.get("figures", True)),
            workers=number("workers", int, 1) if sweep.get("workers") is not None else 1,
            group_shapes=flag("group_shapes", True),
            restarts=number("restarts", int, 0) if sweep.get("restarts") is not None else 2,
            budget=budget,
            max_trials=max_trials,
        )

    def sampler_for(self, trial_index: int) -> "optuna.samplers.BaseSampler":
        """The sampler for the study's ``trial_index``-th trial (seeded per trial: resumes reproduce)."""
        import optuna

        seed = self.seed + trial_index
        if self.sampler == "random":
            return optuna.samplers.RandomSampler(seed=seed)
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=self.n_startup_trials)

    @property
    def pruned_because(self) -> str:
        """How a pruned trial's message ends: what its val.rmse was compared with."""
        if self.pruner == "halving":
            return "outside the best third of the trials that reached this epoch (successive halving)"
        return "worse than the median of earlier trials at this epoch"

    def make_pruner(self) -> "optuna.pruners.BasePruner":
        import optuna

        if self.pruner == "none":
            return optuna.pruners.NopPruner()
        if self.pruner == "halving":  # rungs at m, 3m, 9m … epochs; about a third of the trials go on at each
            return optuna.pruners.SuccessiveHalvingPruner(min_resource=self.pruner_min_epochs, reduction_factor=3)
        return optuna.pruners.MedianPruner(
            n_startup_trials=self.pruner_startup_trials, n_warmup_steps=self.pruner_warmup_epochs
        )



def shape_keys(space: SearchSpace) -> list[str]:
    """The searched keys that shape a stacked solve: those the models of a stack must share
    (:data:`physmend.ude.stack.SHARED_KEYS`, e.g. ``train.segment_length``) and the network's width
    and depth (mixed ones are padded to the largest)."""
    from physmend.ude.stack import SHARED_KEYS

    shaping = (*SHARED_KEYS, "ude.width", "ude.depth")
    return [key for key in space.params if any(key == s or key.startswith(s + ".") for s in shaping)]
