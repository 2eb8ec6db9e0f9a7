"""Where a simulation leaves the range of the records: the divergence of a model as written.

A model as written that lacks a sink or a crowding term may grow without bound within the record
(exponential growth) or blow up in finite time (``dx/dt = a·x²``). Its simulation is then no
reference for anything: normalising a network by values of 1e8, or a training step set by a
Jacobian taken there, makes no sense. This module states the rule and gives the pieces:

* the **range** of a recorded output: the span ``[lo, hi]`` of its records over the fitted
  (training and validation) experiments, at least :data:`MIN_RELATIVE_RANGE` of its magnitude
  wide (a nearly constant record still has a range);
* the **box** of an output: its range widened by :data:`RANGE_MARGIN` ranges on either side —
  the margin by which training holds its states around their range
  (:data:`physmend.ude.shooting.BOX_MARGIN`, the same number): a simulation that goes further
  is outside what any correction trained on these records can reach;
* a simulation **diverges** where an output is not finite, or leaves its box (first such row per
  experiment and output: :func:`first_exits`) and is still leaving it when the record ends (its
  farthest excursion is its last value; :func:`physmend.ude.reference.find_divergence`) — one
  that went out and came back, or turned, is a model that misses, not one that diverges;
* a **projected** right-hand side (:func:`projected`) keeps states inside a box by zeroing the
  rates that point out of it: a model that blows up in finite time can still be simulated, up to
  the time it reaches the box, exactly as written.

Times are in the data's own time unit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import torch

#: a simulated output farther than this many recorded ranges beyond its recorded range has left the
#: data (equal to the training box margin, :data:`physmend.ude.shooting.BOX_MARGIN`)
RANGE_MARGIN = 3.0

#: an output's range is at least this share of its magnitude (equal to
#: :data:`physmend.ude.spec.MIN_RELATIVE_RANGE`: a nearly constant record still has a range)
MIN_RELATIVE_RANGE = 0.1


@dataclass(frozen=True)
class Divergence:
    """One experiment's simulated output (or the state it measures) leaving its box.

    Attributes:
        experiment: the experiment's id; ``role`` its role.
        name: the state the output measures (or the output itself where it measures no one state).
        output: the recorded output.
        time: first time (data time unit, from the experiment's start) outside the box.
        blows_up: True where the model as written could not be simulated past the box (a
            finite-time blow-up: the plain solve failed), False where it grew beyond it.
        low, high: the recorded range of the output; ``box_low``, ``box_high`` its box.
        value: the simulated output at ``time``; ``peak`` the largest magnitude it reached within
            the record (``inf`` where it blew up); ``end`` the record's end (data time unit).
    """

    experiment: str
    role: str
    name: str
    output: str
    time: float
    blows_up: bool
    low: float
    high: float
    box_low: float
    box_high: float
    value: float
    peak: float
    end: float

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def describe(self, time_unit: str = "s", unit: str = "") -> str:
        """One line: which state, from when, against the records."""
        u = f" {unit}" if unit else ""
        head = (f"{self.name} (experiment {self.experiment}, {self.role}) leaves the range of the records "
                f"[{self.low:.3g}, {self.high:.3g}]{u} by more than {RANGE_MARGIN:g} ranges at "
                f"t = {self.time:.4g} {time_unit}")
        if self.blows_up:
            return head + f" and blows up in finite time (the model as written cannot be simulated past it)"
        return head + f" and reaches {self.peak:.3g}{u} by t = {self.end:.4g} {time_unit}"


def recorded_range(obs: torch.Tensor, fitted: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(k,)``: every output's range over the finite records ``obs (T, B, k)``
    of the experiments ``fitted (B,)`` (bool; all where None or none is True), at least
    :data:`MIN_RELATIVE_RANGE` of its magnitude wide (centred); NaN for an output never recorded."""
    if fitted is not None and bool(fitted.any()):
        obs = obs[:, fitted]
    flat = obs.reshape(-1, obs.shape[-1])
    ok = torch.isfinite(flat)
    big = torch.finfo(flat.dtype).max
    lo = torch.where(ok, flat, torch.full_like(flat, big)).amin(0)
    hi = torch.where(ok, flat, torch.full_like(flat, -big)).amax(0)
    none = ~ok.any(0)
    pad = (MIN_RELATIVE_RANGE * torch.maximum(lo.abs(), hi.abs()) - (hi - lo)).clamp_min(0.0) / 2
    lo, hi = lo - pad, hi + pad
    return torch.where(none, torch.nan, lo), torch.where(none, torch.nan, hi)


def box_of(lo: torch.Tensor, hi: torch.Tensor, margin: float = RANGE_MARGIN) -> tuple[torch.Tensor, torch.Tensor]:
    """The range ``[lo, hi]`` widened by ``margin`` ranges on either side; ``∓inf`` where the range
    is unknown (NaN) or empty (an output recorded at exactly zero throughout)."""
    width = hi - lo
    unknown = ~torch.isfinite(width) | (width <= 0)
    return (torch.where(unknown, -math.inf, lo - margin * width),
            torch.where(unknown, math.inf, hi + margin * width))


def first_exits(values: torch.Tensor, box_lo: torch.Tensor, box_hi: torch.Tensor,
                valid: torch.Tensor | None = None) -> torch.Tensor:
    """Row of the first value outside its box (or not finite), per batch element and column:
    ``(B, k)`` long, ``-1`` where it never leaves.

    ``values (T, B, k)``; ``box_lo``, ``box_hi`` broadcast against it; ``valid (T, B)``: rows
    that count (e.g. within each experiment's own record); all where None.
    """
    out = ~torch.isfinite(values) | (values < box_lo) | (values > box_hi)
    if valid is not None:
        out = out & valid[..., None]
    T = values.shape[0]
    rows = torch.arange(T, device=values.device).reshape(T, *([1] * (values.dim() - 1)))
    first = torch.where(out, rows, T).amin(0)
    return torch.where(first < T, first, -1)


def projected(rhs: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], lo: torch.Tensor,
              hi: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """``rhs(u, x)`` held inside the box ``[lo, hi]`` (each broadcast against ``u (B, n)``): the
    rate is taken at ``u`` clamped into the box, and a rate pointing out of the box where ``u`` is
    at or beyond its edge is zero. Inside the box it is ``rhs`` itself."""

    def f(u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        held = torch.clamp(u, lo, hi)
        du = rhs(held, x)
        out = ((u >= hi) & (du > 0)) | ((u <= lo) & (du < 0))
        return torch.where(out, torch.zeros_like(du), du)

    return f
