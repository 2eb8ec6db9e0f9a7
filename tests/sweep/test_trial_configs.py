"""Trial configs without a Hydra composition per trial: a trial of plain values patched into the
sweep's composed base config is the config composing it would give (values, types, struct flag);
anything else is composed; probing a space still fails on a key or a choice that does not compose.

Real composition throughout: ``physmend.config.compose`` is wrapped (delegating to it) only to
count the compositions.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import optuna
import pytest
from omegaconf import DictConfig, OmegaConf

import physmend.config
import physmend.sweep as sw
from physmend.config import ConfigError
from physmend.sweep.configs import TrialComposer

REAL_COMPOSE = physmend.config.compose


@pytest.fixture
def composes(monkeypatch: pytest.MonkeyPatch) -> list[list[str]]:
    """The overrides of every composition from here on (``physmend.config.compose`` delegating)."""
    calls: list[list[str]] = []

    def counted(overrides: Sequence[str] = (), **kwargs: Any) -> DictConfig:
        calls.append(list(overrides))
        return REAL_COMPOSE(overrides, **kwargs)

    monkeypatch.setattr(physmend.config, "compose", counted)
    return calls


def typed(value: Any) -> Any:
    """``value`` (a config as plain containers) with every leaf paired with its type's name."""
    if isinstance(value, dict):
        return {k: typed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [typed(v) for v in value]
    return (type(value).__name__, value)


def composed(overrides: Sequence[str], values: dict[str, Any], config_dir: Path | None) -> DictConfig:
    """The trial's config as the sweep composed it before patching (one full composition)."""
    return REAL_COMPOSE([*overrides, *sw.trial_overrides(values)], user_config_dir=config_dir)


def assert_same(got: DictConfig, want: DictConfig) -> None:
    assert typed(OmegaConf.to_container(got, resolve=False)) == typed(OmegaConf.to_container(want, resolve=False))
    assert OmegaConf.is_struct(got) is OmegaConf.is_struct(want) is True
    assert OmegaConf.is_readonly(got) is OmegaConf.is_readonly(want)


def compositions(composer: TrialComposer, values: dict[str, Any], composes: list[list[str]]) -> tuple[DictConfig, int]:
    """The trial's config from ``composer`` and how many compositions it took."""
    before = len(composes)
    cfg = composer.config(values)
    return cfg, len(composes) - before


def error_of(attempt: Callable[[], Any]) -> str:
    """The message of the ConfigError that ``attempt`` raises."""
    with pytest.raises(ConfigError) as info:
        attempt()
    return str(info.value)


def trials(space: sw.SearchSpace, n_random: int = 5) -> list[dict[str, Any]]:
    """Every example of every parameter (choices, bounds), the space's first trials, and random
    trials drawn by Optuna itself (its value types)."""
    examples = {key: p.examples() for key, p in space.params.items()}
    most = max(len(v) for v in examples.values())
    out = [{key: v[i % len(v)] for key, v in examples.items()} for i in range(most)]
    out += [{**out[0], **t} for t in space.first_trials]
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=3))
    out += [space.suggest(study.ask()) for _ in range(n_random)]
    return out


def check_space(space: sw.SearchSpace, overrides: Sequence[str], config_dir: Path | None,
                composes: list[list[str]]) -> None:
    """Every trial of ``space`` patched (one composition: the base) and equal to composing it."""
    composer = TrialComposer(overrides, config_dir)
    values = trials(space)
    before = len(composes)
    got = [composer.config(v) for v in values]
    assert composes[before:] == [list(overrides)] and composer.patched == len(values)
    for v, cfg in zip(values, got):
        assert_same(cfg, composed(overrides, v, config_dir))


@pytest.mark.parametrize("name", sw.available_spaces())
def test_each_shipped_space_patches_to_the_composed_config(name: str, composes: list[list[str]]) -> None:
    space = sw.load_space(name)
    kinds = {p.kind for p in space.params.values()}
    assert kinds <= {"choice", "log_uniform", "uniform", "int"}
    check_space(space, [], None, composes)


def test_a_user_project_with_group_overrides_patches_too(user_project: Path, composes: list[list[str]]) -> None:
    overrides = ["model=oscillator", "data=oscillator", "simulate=explicit", "train.epochs=4"]
    space = sw.parse_space({"params": {
        "ude.width": {"choice": [4, 8]}, "ude.activation": {"choice": ["tanh", "softplus"]},
        "train.lr": {"log_uniform": [1.0e-5, 0.03]}, "train.weight_decay": {"uniform": [0, 1]},
        "train.segment_samples": {"int": [10, 100], "step": 10}, "simulate.rtol": {"log_uniform": [1e-9, 1e-3]},
        "data.validation_fraction": {"uniform": [0.1, 0.3]}, "train.estimate_parameters": {"choice": [True, False]},
    }}, name="mixed", label="mixed.yaml")
    check_space(space, overrides, user_project / "my_conf", composes)


def test_odd_strings_are_patched_where_hydra_reads_them_back_and_composed_elsewhere(composes: list[list[str]]) -> None:
    composer = TrialComposer([], None)
    assert compositions(composer, {"ude.width": 8}, composes)[1] == 1  # the base
    patched = ["a b", " padded ", "", "1e-3", "true", "null", "it's", 'q"q', "x,y", "[1]", "choice(a)", "é"]
    for text, expected in [*((t, 0) for t in patched), ("${seed}", 1), ("${project:}/x", 1), ("tab\there", 1)]:
        values = {"sweep.study_name": text}
        cfg, n = compositions(composer, values, composes)
        assert n == expected, text
        assert_same(cfg, composed([], values, None))
    # Hydra reads hydra_value's doubled backslash back doubled (physmend.sweep.space): composed as before
    cfg, n = compositions(composer, {"sweep.study_name": "a\\b"}, composes)
    assert n == 1 and cfg.sweep.study_name == composed([], {"sweep.study_name": "a\\b"}, None).sweep.study_name


def test_groups_new_keys_operators_and_odd_types_are_composed(composes: list[list[str]]) -> None:
    import numpy as np

    composer = TrialComposer([], None)
    cases = [({"train.lr": 0.01, "simulate.dtype": "float32"}, 1),  # the first: the base composed, then patched
             ({"simulate": "explicit", "ude.width": 8}, 1), ({"ude": "default"}, 1), ({"operators.add": 2}, 1),
             ({"ude.inputs.states": False}, 0)]
    for values, expected in cases:
        cfg, n = compositions(composer, values, composes)
        assert n == expected, values
        assert_same(cfg, composed([], values, None))
    assert compositions(composer, {"ude.width": np.int64(8)}, composes)[1] == 1  # not a plain int: composed
    patched_error = error_of(lambda: composer.config({"train.nonexistent": 1}))
    assert patched_error == error_of(lambda: composed([], {"train.nonexistent": 1}, None))


def test_a_value_a_rule_refuses_fails_as_composing_does(composes: list[list[str]]) -> None:
    composer = TrialComposer([], None)
    composer.config({"ude.width": 8})
    before = len(composes)
    patched_error = error_of(lambda: composer.config({"ude.width": 0}))
    assert len(composes) == before  # the rule's error, from the patched base
    assert patched_error == error_of(lambda: composed([], {"ude.width": 0}, None))
    assert patched_error == "ude.width must be a whole number in [1, 1024], but got 0"
    composer.config({"ude.width": 16}).ude.width = 3  # a trial's config is its own
    assert composer.config({"ude.depth": 1}).ude.width == REAL_COMPOSE([]).ude.width


@pytest.mark.parametrize(("params", "culprit"), [
    ({"ude.width": {"choice": [4, 8]}, "ude.widht": {"choice": [4, 8]}}, ("ude.widht", 4)),
    ({"ude.width": {"choice": [4, 8]}, "simulate": {"choice": ["default", "nope"]}}, ("simulate", "nope")),
    ({"ude.depth": {"choice": [2, True]}, "train.lr": {"log_uniform": [0.001, 0.01]}}, ("ude.depth", True)),
])
def test_probing_names_the_key_or_choice_that_does_not_compose(
        params: dict[str, Any], culprit: tuple[str, Any], composes: list[list[str]]) -> None:
    space = sw.parse_space({"params": params}, name="bad", label="bad.yaml")
    key, value = culprit
    why = error_of(lambda: composed([], {key: value}, None))
    assert error_of(lambda: sw.probe_space(space, [], None)) == f"bad.yaml: params.{key} = {value!r} does not compose: {why}"


def test_probing_a_shipped_space_composes_once(composes: list[list[str]]) -> None:
    for name in sw.available_spaces():
        before = len(composes)
        sw.probe_space(sw.load_space(name), ["train.epochs=4"], None)
        assert composes[before:] == [["train.epochs=4"]]


def test_a_sweep_s_trial_configs_patch_the_base(composes: list[list[str]]) -> None:
    from physmend.problem import load_problem

    overrides = ["train.epochs=4"]
    cfg = REAL_COMPOSE(overrides)
    configs = sw.TrialConfigs(cfg, load_problem(cfg), overrides, None)
    values = trials(sw.load_space("default"), n_random=3)
    got = [configs.config(v) for v in values]
    assert composes == [overrides]
    for v, trial_cfg in zip(values, got):
        assert_same(trial_cfg, composed(overrides, v, None))
