"""Each trial's configuration (composed from the sweep's overrides plus its values) and problem;
checks that searched keys compose before anything is written.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.config import ConfigError
from physmend.sweep.space import SearchSpace, hydra_value, trial_overrides

if TYPE_CHECKING:
    from physmend.problem import Problem


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")



def check_overrides(space: SearchSpace, overrides: Sequence[str]) -> None:
    """A key set on the command line must not also be searched (which one would win is unclear)."""
    both = sorted({_override_key(o) for o in overrides} & set(space.params))
    if both:
        raise ConfigError(
            f"{', '.join(both)}: set on the command line and searched by {space.label} at once; "
            "remove them from the command line or use a space that does not search them"
        )



def probe_space(space: SearchSpace, overrides: Sequence[str], config_dir: str | Path | None) -> None:
    """Compose trial configs that use every choice (numbers: their low bound), so that a key or a
    choice that does not compose fails before anything is written."""
    from physmend.config import compose

    def attempt(values: dict[str, Any]) -> str | None:
        try:
            compose([*overrides, *trial_overrides(values)], user_config_dir=config_dir)
        except ConfigError as exc:
            return str(exc)
        return None

    first = {key: p.examples()[0] for key, p in space.params.items()}
    probes = [first] + [{**first, key: v} for key, p in space.params.items() if p.kind == "choice" for v in p.choices[1:]]
    for values in probes:
        if attempt(values) is None:
            continue
        for key, value in values.items():  # find the culprit
            error = attempt({key: value})
            if error is not None:
                raise ConfigError(f"{space.label}: params.{key} = {value!r} does not compose: {error}")
        raise ConfigError(f"{space.label}: the trial {values} does not compose: {attempt(values)}")



def check_keys(space: SearchSpace, cfg: DictConfig) -> None:
    """Without overrides to compose from, every searched key must be a value in ``cfg``."""
    for key in space.params:
        node = OmegaConf.select(cfg, key, default="<missing>", throw_on_missing=False)
        if isinstance(node, str) and node == "<missing>" or isinstance(node, DictConfig):
            raise ConfigError(
                f"{space.label}: params.{key} must name a value of the composed config (run the sweep through "
                "the CLI or pass run(..., overrides=...) to search config groups)"
            )



def _touches_problem(key: str) -> bool:
    return key in ("model", "data", "simulate.dtype") or key.startswith(("model.", "data."))



class TrialConfigs:
    """Builds each trial's config and problem; the problem is shared unless a trial changes it.

    A trial's problem has no test experiments (:func:`physmend.ude.metrics.checkpoint_problem`):
    a trial is judged on training and validation data only, and its test metrics would cost a
    whole-trajectory solve of every test record per trial (a long test record: minutes) for figures
    no choice may read. The masked network's retraining and the proposal report the held-out fit.
    """

    def __init__(self, cfg: DictConfig, problem: "Problem", overrides: Sequence[str] | None, config_dir: Any) -> None:
        self.cfg = cfg
        self.overrides = None if overrides is None else list(overrides)
        self.config_dir = config_dir
        from physmend.ude.metrics import checkpoint_problem

        self._problems: dict[tuple[tuple[str, str], ...], Problem] = {(): checkpoint_problem(problem)}

    def config(self, values: dict[str, Any]) -> DictConfig:
        """The composed config of a trial: the sweep's overrides, then the trial's values."""
        if self.overrides is not None:
            from physmend.config import compose

            return compose([*self.overrides, *trial_overrides(values)], user_config_dir=self.config_dir)
        cfg = copy.deepcopy(self.cfg)
        for key, value in values.items():  # no overrides known (called from Python): patch values
            OmegaConf.update(cfg, key, value, merge=False)
        return cfg

    def problem(self, values: dict[str, Any], cfg: DictConfig) -> "Problem":
        from physmend.problem import load_problem
        from physmend.ude.metrics import checkpoint_problem

        key = tuple(sorted((k, hydra_value(v)) for k, v in values.items() if _touches_problem(k)))
        if key not in self._problems:
            self._problems[key] = checkpoint_problem(load_problem(cfg))
        return self._problems[key]
