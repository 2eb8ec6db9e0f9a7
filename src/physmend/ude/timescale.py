"""Time settings derived from the data and the model: no default is an absolute time.

A record may last 3 s at 1 kHz, 30 units of dimensionless time in 40 samples, or 30 days at
5 min; so every time setting whose value is ``auto`` is derived here from

* the **sampling interval** Δ: the median interval between rows with a measured output, over the
  training records (in the data's own time unit);
* the **record length**: the shortest training record (its training part, before a carved
  validation slice);
* the **fastest time constant** of the model as written: ``1 / max |λ|`` over the eigenvalues
  ``λ`` of its Jacobian ``∂f/∂u``, at the start of each training record and, where a reference
  simulation is at hand, along it (central differences: works for any right-hand side).

The rules (``cfg.train`` / ``cfg.symbolic`` keys; a number given instead of ``auto`` wins):

===========================  ======================================================================
``train.step``               ``min(Δ / 2, 2 / max|λ|)``: half a sampling interval, smaller where the
                             fixed-step RK4 of training would be unstable (its stability limit on
                             the real axis is ``|λ h| ≈ 2.8``), then shortened so that a segment
                             holds a whole number of steps
``train.segment_length``     ``train.segment_samples`` · Δ (default 60 samples), at most a quarter
                             of the record, at least 2 steps
``train.warm_window``        ``train.warm_window_samples`` · Δ (default 10), at most a tenth of the
                             record, at least 2 Δ
``symbolic.window``          ``symbolic.window_samples`` · Δ (default 30), at most a tenth of the
                             record, at least 3 Δ
===========================  ======================================================================

An explicit time that cannot work (a step or a segment longer than the record) is one clear error.
Imports: ``physmend.config``, ``physmend.problem`` (the fastest time constant), ``physmend.simulate`` and torch.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from physmend.config import ConfigError
from physmend.problem import fastest_time_constant
from physmend.settings import SymbolicSettings, TrainSettings, TrainingSettings, training_settings

if TYPE_CHECKING:
    from physmend.problem import Problem

AUTO = "auto"
STABLE_RK4 = 2.0  # |λ h| kept below this (RK4's real-axis limit is about 2.785)


class TimeSettingError(ConfigError):
    """A time setting cannot work for these records; the message names the key and the value."""


@dataclass(frozen=True)
class TimeScales:
    """What the data and the model say about time (all in the data's time unit).

    Attributes:
        sample: median sampling interval Δ of the measured outputs over the training records.
        record: length of the shortest training record (its training part).
        fastest: fastest time constant of the model as written, ``1 / max |λ|`` (inf: none).
    """

    sample: float
    record: float
    fastest: float
    notes: list[str] = field(default_factory=list)


def _train_records(problem: Problem) -> list[tuple[np.ndarray, float]]:
    out = []
    for e in problem.experiments:
        if e.role != "train":
            continue
        t = np.asarray(e.obs_time, dtype=float)
        end = float(e.split_time) if e.split_time is not None else float(t[-1])
        out.append((t[t <= end + 1e-12], end))
    return out


def time_scales(problem: Problem, reference: Any | None = None) -> TimeScales:
    """Sampling interval, record length and fastest time constant of ``problem``.

    ``reference``: the model as written simulated on every experiment
    (:func:`physmend.ude.reference.reference`); where given, the Jacobian is also taken along it.
    """
    records = _train_records(problem)
    if not records:
        raise TimeSettingError("deriving time settings needs at least one experiment with role 'train', but there is none")
    gaps = np.concatenate([np.diff(t) for t, _ in records if t.size > 1] or [np.array([])])
    gaps = gaps[gaps > 0]
    record = min(end for _, end in records)
    if gaps.size == 0 or not record > 0:
        raise TimeSettingError(
            f"deriving time settings needs training records with at least two measured rows, but the shortest "
            f"lasts {record:g} time units"
        )
    sample = float(np.median(gaps))
    fastest = fastest_time_constant(problem)
    if reference is not None:
        b_train = [b for b, e in enumerate(problem.experiments) if e.role == "train"]
        T = reference.states.shape[0]
        rows = torch.unique(torch.linspace(0, T - 1, min(T, 16)).round().long())
        st = reference.states[rows][:, b_train].flatten(0, 1)  # (P, n); flatten: m or k may be 0
        xs = reference.inputs[rows][:, b_train].flatten(0, 1)
        ps = reference.batch.params[b_train][None].expand(len(rows), -1, -1).flatten(0, 1)
        ok = torch.isfinite(st).all(-1)
        if bool(ok.any()):
            fastest = min(fastest, fastest_time_constant(problem, st[ok], xs[ok], ps[ok]))
    return TimeScales(sample=sample, record=record, fastest=fastest)


def _given(value: Any) -> float | None:
    """A time setting already checked (:mod:`physmend.settings`): None for ``auto``, else its number."""
    return None if _is_auto(value) else float(value)


def train_times(tc: Any, scales: TimeScales) -> tuple[float, float, float]:
    """``(train.step, train.segment_length, train.warm_window)`` of the ``train`` settings ``tc``
    (:class:`physmend.settings.TrainSettings`) on data and a model with time scales ``scales``: the
    ``auto`` ones derived (see the module docstring), the given ones checked against the record."""
    d, record = scales.sample, scales.record
    segment = _given(tc.segment_length)
    if segment is None:
        segment = min(float(tc.segment_samples) * d, record / 4)
    elif segment > record * (1 + 1e-9):
        raise TimeSettingError(
            f"train.segment_length = {segment:g} is longer than the shortest training record ({record:g} time "
            f"units): give a shorter one, or train.segment_length=auto (train.segment_samples sampling intervals)"
        )
    step = _given(tc.step)
    if step is None:
        limit = STABLE_RK4 * scales.fastest
        step = min(d / 2, limit)
        step = segment / max(2, math.ceil(segment / step - 1e-9))
    elif step >= record:
        raise TimeSettingError(
            f"train.step = {step:g} is not shorter than the shortest training record ({record:g} time units, "
            f"sampled every {d:g}): give a step below the sampling interval, or train.step=auto"
        )
    if segment < step:
        segment = step * 2
    warm = _given(tc.warm_window)
    if warm is None:
        warm = max(2 * d, min(float(tc.warm_window_samples) * d, record / 10))
    return float(step), float(segment), float(warm)


def _window(sc: Any, scales: TimeScales) -> float:
    """``symbolic.window`` of the ``symbolic`` group ``sc`` (checked: :class:`~physmend.settings.SymbolicSettings`):
    ``auto`` derived, else as given."""
    symbolic = SymbolicSettings.build(sc)
    window = _given(symbolic.window)
    if window is None:
        d, record = scales.sample, scales.record
        window = max(3 * d, min(float(symbolic.window_samples) * d, record / 10))
    return float(window)


def resolve_settings(settings: TrainingSettings, problem: Problem, reference: Any | None = None) -> TrainingSettings:
    """``settings`` with the ``auto`` times made numbers from the data and the model (:func:`train_times`);
    ``settings`` itself when they are numbers already. ``reference``: as :func:`time_scales` takes it."""
    if settings.times_resolved:
        return settings
    step, segment, warm = train_times(settings.train, time_scales(problem, reference))
    train = dataclasses.replace(settings.train, step=step, segment_length=segment, warm_window=warm)
    return dataclasses.replace(settings, train=train)


def resolve_times(cfg: Any, problem: Problem, reference: Any | None = None) -> DictConfig:
    """A copy of the configuration ``cfg`` whose ``auto`` time settings are numbers (see the module
    docstring; :func:`resolve_settings` resolves a :class:`~physmend.settings.TrainingSettings`)."""
    out = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    scales = time_scales(problem, reference)
    tc = out.train
    tc.step, tc.segment_length, tc.warm_window = train_times(TrainSettings.build(tc), scales)
    if "symbolic" in out:
        out.symbolic.window = _window(out.symbolic, scales)
    return out


def describe(cfg: Any) -> str:
    """One line with the resolved time settings of ``cfg`` (after :func:`resolve_times`)."""
    tc = cfg.train
    extra = f", symbolic window {float(cfg.symbolic.window):g}" if "symbolic" in cfg else ""
    return (f"time settings: step {float(tc.step):g}, segments {float(tc.segment_length):g}, "
            f"warm-start window {float(tc.warm_window):g}{extra} (data time units)")


GIB = 1024.0**3


def plan_bytes(plan: Any, problem: Problem, cfgs: list[Any]) -> float:
    """Estimated memory (bytes) of one training epoch of ``cfgs`` (one model each) on ``plan``.

    Backpropagation through fixed-step RK4 keeps, for every grid step of every segment and model,
    the four stages' states, inputs and network activations: about
    ``8 · models · S · K · 4 · (12·n + 2·m + 3·Σ widths)`` bytes for ``S`` segments of ``K`` steps,
    ``n`` states, ``m`` inputs; plus the inputs at every half step.
    """
    return steps_bytes(int(plan.steps), int(plan.starts.shape[0]), problem, cfgs)


def steps_bytes(steps: int, segments: int, problem: Problem, cfgs: list[Any]) -> float:
    """:func:`plan_bytes` of a plan of ``segments`` segments of ``steps`` RK4 steps each (known
    before the plan's grid is built)."""
    n, m = len(problem.compiled.state_names), len(problem.compiled.input_names)
    total = int(steps) * int(segments)
    per_model = 0.0
    for cfg in cfgs:
        width, depth = int(cfg.ude.width), int(cfg.ude.depth)
        per_model += 8.0 * total * 4 * (12 * n + 2 * m + 3 * width * max(depth, 1))
    return per_model + 8.0 * (2 * total + segments) * m


def memory_limit(cfg: Any) -> float:
    """``train.memory_limit_gib`` of ``cfg`` (GiB), checked (:mod:`physmend.settings`)."""
    return float(training_settings(cfg).train.memory_limit_gib)


def budget_parts(plan: Any, problem: Problem, cfgs: list[Any]) -> list[list[int]]:
    """The positions of ``cfgs`` in consecutive parts, each a stack whose plan fits
    ``train.memory_limit_gib`` (:func:`steps_bytes`): one part where the whole stack fits; a model
    that does not fit alone is a part of its own (:func:`check_budget` refuses it)."""
    limit = memory_limit(cfgs[0]) * GIB
    steps, segments = int(plan.steps), int(plan.starts.shape[0])
    parts: list[list[int]] = []
    part: list[int] = []
    for i in range(len(cfgs)):
        if part and steps_bytes(steps, segments, problem, [cfgs[j] for j in [*part, i]]) > limit:
            parts.append(part)
            part = []
        part.append(i)
    parts.append(part)
    return parts


def check_budget(plan: Any, problem: Problem, cfgs: list[Any]) -> None:
    """Refuse, in one line, a training plan whose estimated memory exceeds ``train.memory_limit_gib``."""
    check_steps(int(plan.steps), int(plan.starts.shape[0]), float(plan.dt), problem, cfgs)


def check_steps(steps: int, segments: int, dt: float, problem: Problem, cfgs: list[Any]) -> None:
    """:func:`check_budget` of a plan of ``segments`` segments of ``steps`` RK4 steps of ``dt``,
    before anything of that size is allocated."""
    limit = memory_limit(cfgs[0])
    need = steps_bytes(steps, segments, problem, cfgs)
    if need > limit * GIB:
        total = int(steps) * int(segments)
        raise TimeSettingError(
            f"the training plan needs about {need / GIB:.1f} GiB ({total} RK4 steps of {dt:g} over the training "
            f"records x {len(cfgs)} model(s)), more than train.memory_limit_gib={limit:g}: give a larger train.step "
            f"(now {dt:g}), train fewer models at once (sweep.group), or use shorter or fewer training records"
        )


def _is_auto(value: Any) -> bool:
    return value is None or (isinstance(value, str) and value.strip().lower() == AUTO)


def resolved(cfg: Any, problem: Problem) -> Any:
    """``cfg`` itself when its time settings are numbers already, else its times resolved: a
    :class:`~physmend.settings.TrainingSettings` by :func:`resolve_settings`, a configuration by :func:`resolve_times`
    (for entry points that may be called with a freshly composed configuration)."""
    if isinstance(cfg, TrainingSettings):
        return resolve_settings(cfg, problem)
    tc = TrainSettings.build(cfg.train)
    keys = [tc.step, tc.segment_length, tc.warm_window]
    if "symbolic" in cfg:
        keys.append(SymbolicSettings.build(cfg.symbolic).window)
    return resolve_times(cfg, problem) if any(_is_auto(k) for k in keys) else cfg
