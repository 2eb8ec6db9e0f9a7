"""Restarting a trial whose training diverged, before it counts as failed.

A trial's training may diverge for reasons that say little about its architecture: a learning
rate that overshoots on this problem, shooting segments long enough for the hybrid to leave the
data's range, a warm start whose network fits the rates but drives the free simulation away. Such
a trial is trained again (``sweep.restarts`` times at most) with the settings of
:func:`restart_changes`, relative to the trial's own: first smaller steps (``train.lr`` ÷
:data:`LR_DIVISOR`, shooting segments ÷ :data:`SEGMENT_DIVISOR`), then another start (no warm
start). Its Optuna parameters stay what the sampler proposed; its child run records what it was
trained with (tags ``physmend.restarts``, ``physmend.restart.reasons``,
``physmend.restart.overrides``, and the ``config.yaml`` artifact, which later stages load). Only
divergence restarts a trial (:func:`diverged`); a wrong setting or a pruning signal does not.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.settings import TrainSettings

#: each restart divides the trial's learning rate by this
LR_DIVISOR = 3.0

#: each restart divides the trial's shooting-segment length by this
SEGMENT_DIVISOR = 2

#: segments are never made shorter than this many sampling intervals
MIN_SEGMENT_SAMPLES = 2

RESTARTS_TAG = "physmend.restarts"
REASONS_TAG = "physmend.restart.reasons"
OVERRIDES_TAG = "physmend.restart.overrides"
RESTARTS_ATTR = "physmend_restarts"
"""Optuna user attribute of a trial: how many times it was restarted (absent: never)."""


def diverged(exc: BaseException) -> bool:
    """Whether ``exc`` ended a training by divergence: a non-finite loss or trajectory
    (:class:`~physmend.ude.outcome.TrainingDiverged`), a failed simulation
    (:class:`~physmend.simulate.errors.SimulationError`) or a non-finite final metric
    (``FloatingPointError``)."""
    from physmend.simulate.errors import SimulationError
    from physmend.ude.outcome import TrainingDiverged

    return isinstance(exc, (TrainingDiverged, SimulationError, FloatingPointError))


def one_line(exc: BaseException | str, limit: int = 400) -> str:
    """``Type: message`` on one line (whitespace runs folded), at most ``limit`` characters."""
    text = exc if isinstance(exc, str) else f"{type(exc).__name__}: {exc}"
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def restart_changes(cfg: DictConfig, restart: int) -> dict[str, Any]:
    """The settings of restart number ``restart`` (1, 2, …) of a trial configured by ``cfg``, as
    ``{dotted key: value}``.

    Two remedies, in this order: smaller steps — the learning rate ÷ 3 and the shooting segments ÷ 2
    (in sampling intervals where ``train.segment_length`` is ``auto``, else in the segment length's own
    unit), not below :data:`MIN_SEGMENT_SAMPLES` intervals (a length given as a number is halved without
    a floor: its sampling interval is not known here) — then another start: no warm start, the
    trial's own steps (a derivative-matching warm start can give a network that fits the rates yet
    drives the free simulation off its data; every later checkpoint then fails however small the
    steps). Restart 1 takes smaller steps; restart 2 drops the warm start; each further restart takes
    smaller steps again (÷ 3 and ÷ 2 once more). A trial trained without a warm start only takes
    smaller steps (restart ``k``: ``lr / 3**k``, segments ``/ 2**k``)."""
    if restart < 1:
        raise ValueError(f"restart must be >= 1, but got {restart}")
    tc = TrainSettings.build(cfg.train)
    changes: dict[str, Any] = {}
    shrink = restart
    if tc.warm_start != "none" and restart >= 2:
        changes["train.warm_start"] = "none"
        shrink = restart - 2
    if shrink == 0:
        return changes
    changes["train.lr"] = float(tc.lr) / LR_DIVISOR ** shrink
    length = tc.segment_length
    if length == "auto":
        samples = tc.segment_samples
        shorter = max(MIN_SEGMENT_SAMPLES, samples // SEGMENT_DIVISOR ** shrink)
        if shorter < samples:
            changes["train.segment_samples"] = shorter
    else:
        changes["train.segment_length"] = float(length) / SEGMENT_DIVISOR ** shrink
    return changes


def restarted_config(cfg: DictConfig, changes: dict[str, Any]) -> DictConfig:
    """A copy of ``cfg`` with ``changes`` (``{dotted key: value}``) applied."""
    out = copy.deepcopy(cfg)
    for key, value in changes.items():
        OmegaConf.update(out, key, value, merge=False)
    return out


def describe(changes: dict[str, Any]) -> str:
    """``changes`` as Hydra overrides, e.g. ``train.lr=0.00333 train.segment_samples=30``."""
    return " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in changes.items()) or "the same settings"


@dataclass
class Attempts:
    """One trial's training attempts: its own configuration ``cfg``, and the restarts after divergence
    (at most ``limit``), each with :func:`restart_changes` from ``cfg``."""

    cfg: DictConfig
    limit: int
    reasons: list[str] = field(default_factory=list)  # why each earlier attempt failed, one line each
    changes: dict[str, Any] = field(default_factory=dict)  # the settings of the current attempt (none: the first)

    @property
    def restarts(self) -> int:
        return len(self.reasons)

    @property
    def current(self) -> DictConfig:
        """The configuration of the current attempt."""
        return restarted_config(self.cfg, self.changes) if self.changes else self.cfg

    def restart_after(self, exc: BaseException) -> bool:
        """Whether the attempt that raised ``exc`` is followed by another (a divergence, a restart
        left); if so the next attempt's settings are now :attr:`current`."""
        if not diverged(exc) or self.restarts >= self.limit:
            return False
        self.reasons.append(one_line(exc))
        self.changes = restart_changes(self.cfg, self.restarts)
        return True

    def final(self, exc: BaseException) -> BaseException:
        """The error that fails the trial: ``exc``, its message saying which restarts were tried."""
        if not self.reasons or not diverged(exc):
            return exc
        n = self.restarts
        try:
            out = type(exc)(f"{exc} (in restart {n} of {n}, with {describe(self.changes)}; the first attempt: "
                            f"{self.reasons[0]})")
        except Exception:  # noqa: BLE001 - a subclass with another constructor: the error as it is
            return exc
        out.__cause__ = exc
        return out


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` came from a Ctrl-C (a ``KeyboardInterrupt`` in its cause or context chain): a
    signal that lands while a compiled extension initialises comes back as that extension's
    ``ImportError`` ("initialization failed", raised from the interrupt) — no failure of the trial,
    and never restarted."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False
