"""Telemetry loading and validation, experiments, train/validation/test split.

Public face::

    from physmend.data import load_experiments, experiments_by_role

    exps = load_experiments(cfg.data, model.simplify())
    train = experiments_by_role(exps, "train")

See :mod:`physmend.data.config` for the data config schema. Every bad input raises one
:class:`DataError` naming the file, the column or key, and what was expected.
"""

from __future__ import annotations

from physmend.data.config import ROLES, DataConfig, ExperimentSpec, parse_data_config
from physmend.data.errors import DataError
from physmend.data.experiments import (
    Experiment,
    experiments_by_role,
    load_experiments,
    summarize_experiments,
)
from physmend.data.root import resolve_root
from physmend.data.telemetry import Channel

__all__ = [
    "ROLES",
    "Channel",
    "DataConfig",
    "DataError",
    "Experiment",
    "ExperimentSpec",
    "experiments_by_role",
    "load_experiments",
    "parse_data_config",
    "resolve_root",
    "summarize_experiments",
]
