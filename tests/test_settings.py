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
from physmend.settings import (TYPED, SettingError, SimulateSettings, TrainingSettings, TrainSettings,
                               UdeSettings, training_settings)
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
    """A settings class has no default of its own: each field is a key of its group's default.yaml,
    and every key of those files is a field (nothing read loosely elsewhere)."""
    for group, cls in TYPED.items():
        shipped = yaml.safe_load((config_dir() / group / "default.yaml").read_text())
        names = [f.name for f in dataclasses.fields(cls)]
        assert names == list(shipped), group
        assert all(f.default is dataclasses.MISSING for f in dataclasses.fields(cls)), group
    built = training_settings(OmegaConf.create({}))
    assert built == training_settings(compose([]))
    assert built.train.warmup_epochs == 30 and built.train.restarts == 2 and built.train.polish == 0.4


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
