"""The settings of the groups the stages read (``diagnose``, ``mask``, ``sensitivity``, ``symbolic``,
``propose``, ``decide``, ``export``, ``discover``, ``sweep``, ``tracking``) and of the top-level keys
(``seed``, ``threads``, ``device``). Each field is a key of the group's shipped ``default.yaml``
(its default and meaning are there); its type is its rule (:mod:`physmend.settings.rules`).
"""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal, Optional

from annotated_types import Ge, Gt, Le
from pydantic import StringConstraints
from pydantic.dataclasses import dataclass

from physmend.settings.rules import STRICT, Auto, AutoCount, Flag, Free, Group, Kind, Names, Number, Patterns, Whole, Word

#: ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (whether this machine has the device is checked where the
#: problem is loaded, :func:`physmend.device.resolve_device`)
Device = Annotated[str, StringConstraints(pattern=r"(?i)^\s*(auto|cpu|cuda(:\d+)?)\s*$"),
                   Kind("word", words="auto, cpu, cuda or cuda:N (N a device number)")]

Count = Annotated[Whole, Ge(1)]
Share = Annotated[Number, Gt(0), Le(1)]


@dataclass(frozen=True, config=STRICT)
class TopSettings(Group):
    """The top-level keys of ``conf/config.yaml``."""

    GROUP: ClassVar[str] = ""

    seed: Annotated[Whole, Ge(0)]
    threads: AutoCount  # auto: physmend.cpus.threads
    device: Device


@dataclass(frozen=True, config=STRICT)
class TrackingSettings(Group):
    """``tracking.*``: where runs and studies are stored."""

    GROUP: ClassVar[str] = "tracking"

    uri: Word
    experiment: Word
    optuna_storage: Word
    artifact_location: Optional[Word]


@dataclass(frozen=True, config=STRICT)
class DiagnoseSettings(Group):
    """``diagnose.*``: the model as written against every experiment."""

    GROUP: ClassVar[str] = "diagnose"

    n_windows: Count
    window_fraction: Share
    n_correlates: Annotated[Whole, Ge(0)]
    smooth_samples: Count
    plots: Flag


@dataclass(frozen=True, config=STRICT)
class MaskSettings(Group):
    """``mask.*``: the corrections that matter, retrained."""

    GROUP: ClassVar[str] = "mask"

    tolerance: Annotated[Number, Ge(0)]
    max_k: Count
    keep: Optional[Patterns]
    retrain: Flag
    retrain_epochs: Count
    retrain_fit_gain: Annotated[Number, Ge(0), Le(0.5)]
    rivals: Annotated[Whole, Ge(0)]
    workers: Auto
    train_overrides: Patterns


@dataclass(frozen=True, config=STRICT)
class SensitivitySettings(Group):
    """``sensitivity.*``: the inputs the kept corrections depend on."""

    GROUP: ClassVar[str] = "sensitivity"

    top_k: Count
    inputs: Optional[Patterns]
    group_r: Optional[Share]
    max_rows: Count


@dataclass(frozen=True, config=STRICT)
class SymbolicSettings(Group):
    """``symbolic.*``: the kept corrections as formulas."""

    GROUP: ClassVar[str] = "symbolic"

    backend: Word  # checked by the back-end registry (pysr is optional)
    select: Literal["recorded", "rule"]
    window: Auto
    window_samples: Count
    rule: Literal["score", "knee", "best", "bic"]
    choice: Free  # {state: Pareto index}, checked against each front
    parameters: Names
    options: Free  # checked by the back end
    units: Flag
    refit_epochs: Annotated[Whole, Ge(0)]
    recalibrate: Flag
    verbose: Flag
    canonical_r2: Share


@dataclass(frozen=True, config=STRICT)
class ProposeSettings(Group):
    """``propose.*``: the corrected model on training and held-out experiments."""

    GROUP: ClassVar[str] = "propose"

    plots: Flag


@dataclass(frozen=True, config=STRICT)
class DecideSettings(Group):
    """``decide.*``: ``physmend accept`` / ``reject``."""

    GROUP: ClassVar[str] = "decide"

    output_dir: Word
    reason: Word


@dataclass(frozen=True, config=STRICT)
class ExportSettings(Group):
    """``export.*``: a proposal's corrected model as files."""

    GROUP: ClassVar[str] = "export"

    output_dir: Word
    format: Literal["all", "latex", "sympy", "python", "network", "petab"]


@dataclass(frozen=True, config=STRICT)
class DiscoverSettings(Group):
    """``discover.*``: every stage end to end (the sweep's keys it sets)."""

    GROUP: ClassVar[str] = "discover"

    n_trials: Count
    budget: Optional[Annotated[Number, Gt(0)]]
    max_trials: Optional[Count]
    space: Word
    group: Count
    group_shapes: Flag
    workers: AutoCount  # auto: the CPUs this process may use, at most n_trials


@dataclass(frozen=True, config=STRICT)
class SweepSettings(Group):
    """``sweep.*``: the Optuna study of architectures (:class:`physmend.sweep.Settings` adds what it makes)."""

    GROUP: ClassVar[str] = "sweep"

    space: Word
    n_trials: Count
    budget: Optional[Annotated[Number, Gt(0)]]
    max_trials: Optional[Count]
    restarts: Annotated[Whole, Ge(0)]
    study_name: Optional[Word]
    sampler: Literal["tpe", "random"]
    n_startup_trials: Annotated[Whole, Ge(0)]
    pruner: Literal["median", "halving", "none"]
    pruner_startup_trials: Annotated[Whole, Ge(0)]
    pruner_warmup_epochs: Annotated[Whole, Ge(0)]
    pruner_min_epochs: Count
    seed: Annotated[Whole, Ge(0)]
    timeout: Optional[Annotated[Number, Ge(0)]]
    max_failures_in_a_row: Annotated[Whole, Ge(0)]
    heartbeat_interval: Count
    stale_after: Count
    group: Count
    group_shapes: Flag
    progress: Flag
    workers: Count
    figures: Flag
