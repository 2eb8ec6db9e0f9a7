"""Each trial's configuration (composed from the sweep's overrides plus its values) and problem;
checks that searched keys compose before anything is written.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, ListConfig, OmegaConf

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



_PLAIN_TYPES = (type(None), bool, int, float, str)



def _plain_value(value: Any) -> bool:
    """Whether ``value`` lands in the config as itself both when Hydra parses it from
    :func:`hydra_value`'s text and when it is set directly: None, a bool, an int, a float, or a
    printable string without ``$`` (an interpolation, the ``${project:}`` placeholder among them,
    which :func:`physmend.config.compose` substitutes) and without a backslash (Hydra reads back
    ``hydra_value``'s escapes only before a quote)."""
    if type(value) not in _PLAIN_TYPES:  # exact types: a numpy float is written as another text
        return False
    return not isinstance(value, str) or (value.isprintable() and "$" not in value and "\\" not in value)



def _is_leaf(cfg: DictConfig, key: str) -> bool:
    """Whether the dotted ``key`` names a value that is set in ``cfg``: every step a mapping, the
    last one a value (not a mapping or list, not missing), interpolations unresolved."""
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or node._is_none() or node._is_missing():  # noqa: SLF001
            return False
        if node._is_interpolation():  # noqa: SLF001 - a mapping given as ${...}
            return False
        node = node._get_node(part, validate_access=False)  # noqa: SLF001 - the node itself, unresolved
        if node is None:
            return False
    return not isinstance(node, (DictConfig, ListConfig)) and not node._is_missing()  # noqa: SLF001



class TrialComposer:
    """Each trial's config from the sweep's Hydra ``overrides`` followed by the trial's values.

    Composing costs about half a second. A trial that only sets values (:func:`_plain_value`) of
    keys the sweep's base config already has as values (:func:`_is_leaf`), none under
    ``operators.``, gets a deep copy of that base (composed once, on first use) with its values set
    and checked by the rules :func:`physmend.config.compose` checks (``check_settings``): the same
    config, types and flags as composing. Any other trial (a group choice, a new key, a value Hydra
    would read otherwise) is composed in full.
    """

    def __init__(self, overrides: Sequence[str], config_dir: str | Path | None) -> None:
        self.overrides = list(overrides)
        self.config_dir = config_dir
        self._base: DictConfig | None = None
        self._base_failed = False
        self.patched = 0  # trials answered by patching the base, for tests and profiles

    def config(self, values: dict[str, Any]) -> DictConfig:
        """The trial's config: the base patched where that is the same as composing, else composed."""
        cfg = self._patched(values)
        if cfg is not None:
            self.patched += 1
            return cfg
        from physmend.config import compose

        return compose([*self.overrides, *trial_overrides(values)], user_config_dir=self.config_dir)

    def _base_config(self) -> DictConfig | None:
        """The sweep's overrides composed (once); None where they do not compose on their own."""
        if self._base is None and not self._base_failed:
            from physmend.config import compose

            try:
                self._base = compose(self.overrides, user_config_dir=self.config_dir)
            except ConfigError:
                self._base_failed = True  # every trial composed in full: it reports the error
        return self._base

    def _patched(self, values: dict[str, Any]) -> DictConfig | None:
        """The base with ``values`` set and checked, or None where only composing says what it is."""
        if any(key.startswith("operators.") or not _plain_value(v) for key, v in values.items()):
            return None
        base = self._base_config()
        if base is None or not all(_is_leaf(base, key) for key in values):
            return None
        from physmend.config_check import check_settings
        from physmend.settings import SettingError

        cfg = copy.deepcopy(base)
        OmegaConf.set_struct(cfg, False)  # as compose checks: struct off, then on
        for key, value in values.items():
            OmegaConf.update(cfg, key, value, merge=False)
        try:
            check_settings(cfg)
        except SettingError as exc:
            raise ConfigError(str(exc)) from None
        OmegaConf.set_struct(cfg, True)
        return cfg



def probe_space(space: SearchSpace, overrides: Sequence[str], config_dir: str | Path | None) -> None:
    """Compose trial configs that use every choice (numbers: their low bound), so that a key or a
    choice that does not compose fails before anything is written (a trial of plain values patched
    into the composed base config and checked as :func:`physmend.config.compose` checks it)."""
    composer = TrialComposer(overrides, config_dir)

    def attempt(values: dict[str, Any]) -> str | None:
        try:
            composer.config(values)
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
        self._composer = None if overrides is None else TrialComposer(overrides, config_dir)
        from physmend.ude.metrics import checkpoint_problem

        self._problems: dict[tuple[tuple[str, str], ...], Problem] = {(): checkpoint_problem(problem)}

    def config(self, values: dict[str, Any]) -> DictConfig:
        """The composed config of a trial: the sweep's overrides, then the trial's values
        (:class:`TrialComposer`: values of existing keys patched into the composed base config)."""
        if self._composer is not None:
            return self._composer.config(values)
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
