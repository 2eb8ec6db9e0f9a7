"""The settings of the groups training reads: ``train``, ``ude`` (with ``ude.inputs``) and ``simulate``,
and :class:`TrainingSettings`, everything a training reads, built once (:func:`training_settings`).

``auto`` times (``train.step``, ``train.segment_length``, ``train.warm_window``) are resolved once
per training by :func:`physmend.ude.timescale.resolve_settings` (the rules are there).

A :class:`TrainingSettings` reads like the configuration it came from (``s.train.lr``,
``s.ude.inputs.states``, ``s.simulate.method``, ``s.seed``), so code that takes either reads both.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, ClassVar, Literal

from annotated_types import Ge, Gt, Le
from pydantic.dataclasses import dataclass

from physmend.settings.rules import (AUTO, STRICT, Auto, Flag, Free, Group, Names, Number, Patterns, Switch,
                                     Whole, Word)
from physmend.settings.stages import TopSettings


@dataclass(frozen=True, config=STRICT)
class TrainSettings(Group):
    """``train.*``: multiple-shooting training (see ``conf/train/default.yaml`` for each key's meaning).

    Times are in the data's time unit; ``step``, ``segment_length`` and ``warm_window`` are
    ``'auto'`` or a number until :func:`physmend.ude.timescale.resolve_settings` makes them numbers.
    """

    GROUP: ClassVar[str] = "train"

    epochs: Annotated[Whole, Ge(1)]
    lr: Annotated[Number, Gt(0)]
    weight_decay: Annotated[Number, Ge(0)]
    schedule: Literal["cosine", "none"]
    step: Auto
    segment_length: Auto
    segment_samples: Annotated[Whole, Ge(1)]
    continuity_weight: Annotated[Number, Ge(0)]
    eval_every: Annotated[Whole, Ge(1)]
    patience: Annotated[Whole, Ge(0)]
    patience_fit_gain: Annotated[Number, Ge(0), Le(0.5)]
    polish: Annotated[Number, Ge(0)]
    restarts: Annotated[Whole, Ge(0)]
    estimate_parameters: Flag
    warm_start: Literal["auto", "none"]
    warm_iterations: Annotated[Whole, Ge(0)]
    warm_window: Auto
    warm_window_samples: Annotated[Whole, Ge(1)]
    segment_starts: Literal["chained", "forced"]
    warmup_epochs: Annotated[Whole, Ge(0)]
    sparsity: Annotated[Number, Ge(0)]
    backward: Literal["autograd", "adjoint"]
    memory_limit_gib: Annotated[Number, Gt(0)]

    @property
    def chained(self) -> bool:
        """``segment_starts == 'chained'``: after a warm start, segments start where the previous one ends."""
        return self.segment_starts == "chained"

    @property
    def cycles(self) -> int:
        """Cycles of ``epochs`` a model may get: the first and ``restarts`` more."""
        return 1 + self.restarts

    @property
    def polish_iterations(self) -> int:
        """L-BFGS iterations after Adam: ``polish`` as a share of ``epochs`` (0: none)."""
        return int(round(self.polish * self.epochs))

    @property
    def warm_window_steps(self) -> int:
        """The warm-start window in training steps (at least 1; times resolved)."""
        return max(1, int(round(float(self.warm_window) / float(self.step))))


#: the widest hidden layer and the most hidden layers a network may have (``ude.width``, ``ude.depth``),
#: generous bounds (a sweep's shipped spaces search widths 4-64 and 1-3 layers) that keep any network,
#: and one read back from a store, under ~150 MB of weights: ``hybrid.json`` is checked against them
#: before its network is built (:mod:`physmend.ude.stored_spec`)
MAX_UNITS = 1024
MAX_LAYERS = 16


@dataclass(frozen=True, config=STRICT)
class InputsSettings(Group):
    """``ude.inputs.*``: the network's inputs (lists of names/patterns as tuples)."""

    GROUP: ClassVar[str] = "ude"

    states: Switch
    observed: Names
    inputs: Switch
    parameters: Names


@dataclass(frozen=True, config=STRICT)
class UdeSettings(Group):
    """``ude.*``: the hybrid model (see ``conf/ude/default.yaml``)."""

    GROUP: ClassVar[str] = "ude"

    corrected: Patterns
    inputs: InputsSettings
    width: Annotated[Whole, Ge(1), Le(MAX_UNITS)]
    depth: Annotated[Whole, Ge(0), Le(MAX_LAYERS)]
    activation: Word  # checked against the activations where the network is built
    units: Literal["equation", "state"]
    output_scale: Annotated[Number, Gt(0)]


@dataclass(frozen=True, config=STRICT)
class SimulateSettings(Group):
    """``simulate.*``: whole-trajectory simulation (see ``conf/simulate/default.yaml``)."""

    GROUP: ClassVar[str] = "simulate"

    method: Word  # checked by the solver registry
    rtol: Annotated[Number, Gt(0)]
    atol: Annotated[Number, Gt(0)]
    dtype: Literal["float64", "float32"]
    options: Free

    def solver(self) -> dict[str, Any]:
        """The solver options of every whole-trajectory simulation (``method``, ``rtol``, ``atol``, ``options``)."""
        return {"method": str(self.method), "rtol": float(self.rtol), "atol": float(self.atol),
                "options": dict(self.options or {})}


@dataclasses.dataclass(frozen=True)
class TrainingSettings:
    """Everything a training reads: ``seed`` and the ``train``, ``ude`` and ``simulate`` groups."""

    seed: int
    train: TrainSettings
    ude: UdeSettings
    simulate: SimulateSettings

    @property
    def times_resolved(self) -> bool:
        t = self.train
        return not any(v == AUTO for v in (t.step, t.segment_length, t.warm_window))


def training_settings(cfg: Any) -> TrainingSettings:
    """The :class:`TrainingSettings` of ``cfg`` (a composed or hand-built configuration; returned as
    is when it is one already). A missing group or key gets its shipped default; a missing ``seed`` the one of ``conf/config.yaml``."""
    if isinstance(cfg, TrainingSettings):
        return cfg
    get = cfg.get if hasattr(cfg, "get") else (lambda key, default=None: getattr(cfg, key, default))
    seed = get("seed", None)
    seed = TopSettings.check("seed", TopSettings.default("seed") if seed is None else seed)
    return TrainingSettings(seed=seed, train=TrainSettings.build(get("train", None)),
                            ude=UdeSettings.build(get("ude", None)),
                            simulate=SimulateSettings.build(get("simulate", None)))
