"""Typed settings of every group physmend ships, built once from the composed configuration.

Each group (``train``, ``ude``, ``simulate``, ``sweep``, ``symbolic`` …, and the top-level ``seed``,
``threads``, ``device``) is a frozen pydantic dataclass whose fields are exactly the group's keys
(:data:`TYPED`). Its defaults live in one place, the shipped YAML (``conf/<group>/default.yaml``): a
key missing from a configuration built in code gets its shipped default, never a default of the
code's. Every rule (kind, range, choices) is a field's type, checked when the settings are built
(:func:`group_settings`, :func:`training_settings`) and when a configuration is composed
(:mod:`physmend.config_check` checks each key by it), with messages that name the key, the rule and
the value (``train.epochs must be a whole number ≥ 1, but got 0``). Code reads a group through its
settings object, never the raw keys.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from physmend.settings.rules import AUTO, Group, Rule, check_field, rule_of
from physmend.settings.shipped import SettingError, shipped_default, shipped_dir, shipped_group
from physmend.settings.stages import (DecideSettings, DiagnoseSettings, DiscoverSettings, ExportSettings,
                                      MaskSettings, ProposeSettings, SensitivitySettings, SweepSettings,
                                      SymbolicSettings, TopSettings, TrackingSettings)
from physmend.settings.training import (MAX_LAYERS, MAX_UNITS, InputsSettings, SimulateSettings, TrainingSettings,
                                        TrainSettings, UdeSettings, training_settings)

#: every settings class, by the group it types (``""``: the top-level keys of ``conf/config.yaml``)
TYPED: dict[str, type[Group]] = {
    "": TopSettings, "simulate": SimulateSettings, "tracking": TrackingSettings, "diagnose": DiagnoseSettings,
    "ude": UdeSettings, "train": TrainSettings, "mask": MaskSettings, "sensitivity": SensitivitySettings,
    "symbolic": SymbolicSettings, "propose": ProposeSettings, "decide": DecideSettings, "export": ExportSettings,
    "discover": DiscoverSettings, "sweep": SweepSettings,
}


def group_settings(cfg: Any, group: str) -> Any:
    """The settings of ``group`` of ``cfg`` (a composed or hand-built configuration), checked; a
    missing group or key gets its shipped default. ``""``: the top-level keys (:class:`TopSettings`)."""
    cls = TYPED[group]
    if not group:
        keys = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
        return cls.build({key: cfg[key] for key in keys if key in cfg and cfg[key] is not None})
    return cls.build(cfg.get(group, None) if hasattr(cfg, "get") else getattr(cfg, group, None))


__all__ = [
    "AUTO", "MAX_LAYERS", "MAX_UNITS", "TYPED", "DecideSettings", "DiagnoseSettings", "DiscoverSettings",
    "ExportSettings", "InputsSettings", "MaskSettings", "ProposeSettings", "Rule", "SensitivitySettings",
    "SettingError", "SimulateSettings", "SweepSettings", "SymbolicSettings", "TopSettings", "TrackingSettings",
    "TrainSettings", "TrainingSettings", "UdeSettings", "check_field", "group_settings", "rule_of",
    "shipped_default", "shipped_dir", "shipped_group", "training_settings",
]
