"""The ``sweep.*`` options, checked on construction; the sampler and the pruner they make; the
searched keys that shape a stacked solve.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from physmend.config import ConfigError
from physmend.settings import SettingError, SweepSettings, rule_of
from physmend.sweep.space import SearchSpace

if TYPE_CHECKING:
    import optuna

    from physmend.sweep.budget import Budget


#: the samplers and the pruners ``sweep.sampler`` and ``sweep.pruner`` name (the rules of their fields)
SAMPLERS: tuple[str, ...] = rule_of(SweepSettings, "sampler").choices  # type: ignore[union-attr]
PRUNERS: tuple[str, ...] = rule_of(SweepSettings, "pruner").choices  # type: ignore[union-attr]


class Settings(SweepSettings):
    """``cfg.sweep``, checked (:class:`physmend.settings.SweepSettings`: every key, its default in
    ``conf/sweep/default.yaml``), with the sampler, the pruner and the budget it makes.

    ``restarts``: trainings of a diverged trial restarted before it fails (:mod:`physmend.sweep.restart`).
    ``budget`` (s of wall time, None: none) and ``max_trials``: the study has ``n_trials`` trials at
    least and as many more as the budget allows, ``max_trials`` at most (:mod:`physmend.sweep.budget`).
    """

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
        """The settings of the ``sweep`` group ``sweep``; a wrong one is a :class:`ConfigError`."""
        try:
            return cls.build(sweep, "sweep")
        except SettingError as exc:
            raise ConfigError(str(exc)) from None

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


def proposed_together(space: SearchSpace, settings: Settings, count: int) -> list[dict[str, Any]]:
    """The values of a new study's first ``count`` trials as one group of ``count`` is proposed
    (:meth:`physmend.sweep.group.StackedTrials.trial_group`, ``sweep.group_shapes`` aside): the
    space's ``first_trials`` first, every trial asked before any is suggested, the sampler of the
    last one asked suggesting them all. Computed on an in-memory study: nothing is stored."""
    import optuna

    study = optuna.create_study(direction="minimize")
    for values in space.first_trials:
        study.enqueue_trial(values, skip_if_exists=True)
    trials = []
    for _ in range(count):
        study.sampler = settings.sampler_for(len(study.get_trials(deepcopy=False)))
        trials.append(study.ask())
    return [space.suggest(trial) for trial in trials]
