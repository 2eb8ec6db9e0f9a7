"""Typed settings built once: the shipped YAML holds every default, a configuration built in code
trains exactly like one composed from the YAML, and every rule names the key, the rule and the value."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
import yaml
from omegaconf import OmegaConf

from physmend.config import ConfigError, compose, config_dir
from physmend.problem import load_problem
from physmend.settings import (TYPED, SettingError, SimulateSettings, SweepSettings, TrainingSettings, TrainSettings,
                               UdeSettings, group_settings, rule_of, shipped_group, training_settings)
from physmend.ude import train
from physmend.ude.warmstart import forget_warm_starts

#: what a user writes for a short training of the oscillator of tests/conftest.py
WRITTEN = {"train": {"step": 0.05, "segment_length": 3.0, "epochs": 6, "eval_every": 2, "lr": 0.02,
                     "warm_iterations": 50, "warmup_epochs": 2},
           "ude": {"width": 8, "depth": 1},
           "simulate": {"method": "dopri5", "rtol": 1e-5, "atol": 1e-6}}


def _overrides(written: dict) -> list[str]:
    return [f"{group}.{key}={value}" for group, keys in written.items() for key, value in keys.items()]


def test_every_default_lives_in_the_shipped_yaml() -> None:
    """A settings class has no default of its own: each field is a key of its group's default.yaml
    (the top-level keys: of config.yaml), and every key of those files is a field (nothing read
    loosely elsewhere)."""
    for group, cls in TYPED.items():
        shipped = shipped_group(group)
        if group:
            assert shipped == yaml.safe_load((config_dir() / group / "default.yaml").read_text())
        names = [f.name for f in dataclasses.fields(cls)]
        assert names == list(shipped), group
        assert all(f.default is dataclasses.MISSING for f in dataclasses.fields(cls)), group
        # built from nothing: the shipped YAML's values, the same as from the composed configuration
        assert group_settings(OmegaConf.create({}), group) == group_settings(compose([]), group), group
    built = training_settings(OmegaConf.create({}))
    assert built == training_settings(compose([]))
    assert built.train.warmup_epochs == 30 and built.train.restarts == 2 and built.train.polish == 0.4
    assert group_settings({}, "sweep").seed == 0 and group_settings({}, "symbolic").canonical_r2 == 0.995


def test_every_shipped_group_is_typed() -> None:
    """Every group physmend ships the keys of has a settings class (the user's model, data and
    operators are checked where they are read)."""
    shipped = {p.name for p in config_dir().iterdir() if p.is_dir()} - {"model", "data", "operators"}
    assert shipped == set(TYPED) - {""}
    assert set(TYPED[""].__pydantic_fields__) == {"seed", "threads", "device"}


def test_every_group_checks_its_keys_and_values() -> None:
    """An unknown key or a value against its field's rule, in any group: a :class:`SettingError`
    naming the key and the rule, when the settings are built and when the configuration is composed."""
    with pytest.raises(SettingError, match=r"^symbolic.bakend is not a setting of symbolic; the settings are: "
                                           r"backend, select, window"):
        group_settings(OmegaConf.create({"symbolic": {"bakend": "sindy"}}), "symbolic")
    with pytest.raises(SettingError, match=r"^thread is not a setting of the configuration; the settings are: seed"):
        TYPED[""].build({"thread": 2})
    with pytest.raises(ConfigError, match=r"^sweep.trials is not a setting of sweep; the settings are: space, n_trials"):
        compose(["+sweep.trials=3"])  # when composed too, before anything runs
    cases = [("sweep.sampler", "grid", "sweep.sampler must be one of ['tpe', 'random'], but got 'grid'"),
             ("sweep.budget", 0, "sweep.budget must be a number > 0, but got 0"),
             ("sweep.max_trials", 0.5, "sweep.max_trials must be a whole number ≥ 1, but got 0.5"),
             ("mask.retrain_fit_gain", 0.9, "mask.retrain_fit_gain must be a number in [0, 0.5], but got 0.9"),
             ("mask.workers", 0, "mask.workers must be 'auto' or a number > 0, but got 0"),
             ("mask.keep", "cart.v", "mask.keep must be a list of names/patterns, but got 'cart.v'"),
             ("sensitivity.group_r", 2, "sensitivity.group_r must be a number in (0, 1], but got 2"),
             ("diagnose.plots", "yes", "diagnose.plots must be true or false, but got 'yes'"),
             ("diagnose.n_windows", True, "diagnose.n_windows must be a whole number ≥ 1, but got True"),
             ("symbolic.rule", "elbow", "symbolic.rule must be one of ['score', 'knee', 'best', 'bic'], but got 'elbow'"),
             ("symbolic.window", "soon", "symbolic.window must be 'auto' or a number > 0, but got 'soon'"),
             ("export.format", "pdf", "export.format must be one of ['all', 'latex', 'sympy', 'python', 'network', "
                                      "'petab'], but got 'pdf'"),
             ("discover.group_shapes", "no", "discover.group_shapes must be true or false, but got 'no'"),
             ("tracking.uri", 3, "tracking.uri must be a word, but got 3"),
             ("threads", 0, "threads must be 'auto' or a whole number ≥ 1, but got 0"),
             ("device", "gpu", "device must be auto, cpu, cuda or cuda:N (N a device number), but got 'gpu'")]
    for key, value, message in cases:
        group, _, name = key.rpartition(".")
        with pytest.raises(SettingError) as info:
            TYPED[group].build({name: value})
        assert str(info.value) == message
        with pytest.raises(ConfigError) as composed:
            compose([f"{key}={value!r}" if isinstance(value, str) else f"{key}={value}"])
        assert message in str(composed.value), key


def test_values_are_read_as_the_rules_say() -> None:
    """Text that reads as a number is that number, a whole number may be written 2.0 (not 2.5), a
    switch is true or false only, a list becomes a tuple, null is allowed where the YAML says what it means."""
    sweep = SweepSettings.build({"budget": "1e2", "n_trials": 2.0, "timeout": None, "study_name": None})
    assert sweep.budget == 100.0 and sweep.n_trials == 2 and isinstance(sweep.n_trials, int) and sweep.timeout is None
    for bad in ({"n_trials": 2.5}, {"progress": 1}, {"seed": -1}, {"heartbeat_interval": float("inf")}):
        with pytest.raises(SettingError):
            SweepSettings.build(bad)
    mask = group_settings({"mask": {"keep": ["cart.v"], "workers": "2"}}, "mask")
    assert mask.keep == ("cart.v",) and mask.workers == 2.0
    assert group_settings({"sensitivity": {"group_r": None}}, "sensitivity").group_r is None
    assert compose(["sweep.budget=1e2", "threads=2.0"]).sweep.budget == 100.0
    assert rule_of(SweepSettings, "pruner").choices == ("median", "halving", "none")  # the rule is the field's type
    with pytest.raises(dataclasses.FrozenInstanceError):
        sweep.n_trials = 3  # type: ignore[misc]


def test_rules_name_the_key_the_rule_and_the_value() -> None:
    cases = [({"train": {"epochs": 0}}, "train.epochs must be a whole number ≥ 1, but got 0"),
             ({"train": {"lr": -1}}, "train.lr must be a number > 0, but got -1"),
             ({"train": {"patience_fit_gain": 0.9}}, "train.patience_fit_gain must be a number in [0, 0.5], but got 0.9"),
             ({"train": {"schedule": "linear"}}, "train.schedule must be one of ['cosine', 'none'], but got 'linear'"),
             ({"train": {"step": "soon"}}, "train.step must be 'auto' or a number > 0, but got 'soon'"),
             ({"train": {"estimate_parameters": "yes"}}, "train.estimate_parameters must be true or false, but got 'yes'"),
             ({"ude": {"width": 4096}}, "ude.width must be a whole number in [1, 1024], but got 4096"),
             ({"ude": {"inputs": {"states": "all"}}}, "ude.inputs.states must be true, false or a list of names/patterns, but got 'all'"),
             ({"simulate": {"dtype": "float16"}}, "simulate.dtype must be one of ['float64', 'float32'], but got 'float16'"),
             ({"train": {"epoch": 3}}, "train.epoch is not a setting of train; the settings are: epochs, lr")]
    for cfg, message in cases:
        with pytest.raises(SettingError) as info:
            training_settings(OmegaConf.create(cfg))
        assert message in str(info.value)
    # the same rules when a configuration is composed, before anything runs
    with pytest.raises(ConfigError, match=r"train.warmup_epochs must be a whole number ≥ 0, but got -2"):
        compose(["train.warmup_epochs=-2"])
    assert compose(["train.lr=1e-3"]).train.lr == 1e-3  # text that reads as a number is that number


def test_settings_are_frozen_and_built_once() -> None:
    settings = training_settings(compose([]))
    assert training_settings(settings) is settings
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.train.epochs = 3  # type: ignore[misc]
    assert isinstance(settings, TrainingSettings) and isinstance(settings.train, TrainSettings)
    assert isinstance(settings.ude, UdeSettings) and isinstance(settings.simulate, SimulateSettings)
    assert settings.ude.corrected == ("*",)  # lists become tuples


def test_a_configuration_built_in_code_trains_exactly_like_a_composed_one(user_project: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Only the keys a user writes, in code, against the same keys composed from the shipped YAML:
    the same settings, the same checkpoints, the same weights (bit for bit)."""
    monkeypatch.chdir(user_project)
    composed = compose(["model=oscillator", "data=oscillator", *_overrides(WRITTEN)],
                       user_config_dir=user_project / "my_conf")
    built = OmegaConf.create({"model": OmegaConf.to_container(composed.model),
                              "data": OmegaConf.to_container(composed.data), **WRITTEN})
    assert training_settings(built) == training_settings(composed)
    problem = load_problem(composed)
    ours = train(built, problem)
    forget_warm_starts()  # each fits its own warm start
    theirs = train(composed, problem)
    assert repr(ours.history) == repr(theirs.history) and len(ours.history) > 3  # repr: NaN losses equal too
    for key, value in theirs.hybrid.state_dict().items():
        assert torch.equal(ours.hybrid.state_dict()[key], value), key
