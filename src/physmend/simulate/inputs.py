"""Exogenous inputs as batched piecewise-linear functions of time."""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np
import torch


class PiecewiseLinear:
    """Linear interpolation of ``values (B, K, n)`` on shared knots ``knots (K,)`` (seconds).

    Outside the knots the end values are held. ``__call__(t)`` with a scalar ``t`` gives
    ``(B, n)``; :meth:`at` with ``t (T,)`` gives ``(T, B, n)``.
    """

    def __init__(self, knots: torch.Tensor, values: torch.Tensor) -> None:
        if knots.ndim != 1 or values.ndim != 3 or values.shape[1] != knots.shape[0]:
            raise ValueError(
                f"PiecewiseLinear needs knots (K,) and values (B, K, n), but got {tuple(knots.shape)} "
                f"and {tuple(values.shape)}"
            )
        self.knots = knots
        self.values = values
        self._knot_list = knots.tolist()  # scalar calls (one per solver stage) find their interval by bisection
        self._rows = torch.arange(values.shape[0])
        k = knots.shape[0]
        if k > 1:
            dt = (knots[1:] - knots[:-1]).clamp_min(1e-300)
            self.slopes = (values[:, 1:] - values[:, :-1]) / dt[None, :, None]
        else:
            self.slopes = torch.zeros_like(values)

    @property
    def n_inputs(self) -> int:
        return self.values.shape[-1]

    def _index(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = self.knots.shape[0]
        tc = t.clamp(self.knots[0], self.knots[-1])
        idx = (torch.searchsorted(self.knots, tc.detach().reshape(-1), right=True) - 1).clamp(0, max(k - 2, 0))
        return idx.reshape(t.shape), tc

    def __call__(self, t: torch.Tensor | float) -> torch.Tensor:
        if (isinstance(t, float) or (isinstance(t, torch.Tensor) and t.ndim == 0 and not t.requires_grad)) \
                and self.values.shape[-1] and len(self._knot_list) > 1:
            # one time (the solvers' case): a few tensor operations instead of a vectorised search
            knots = self._knot_list
            tc = min(max(float(t), knots[0]), knots[-1])
            i = min(max(bisect.bisect_right(knots, tc) - 1, 0), len(knots) - 2)
            return self.values[:, i] + self.slopes[:, i] * (tc - knots[i])
        t = torch.as_tensor(t, dtype=self.knots.dtype, device=self.knots.device)
        if self.values.shape[-1] == 0:
            return self.values[:, 0, :]
        idx, tc = self._index(t)
        base = self.values[:, idx]
        if self.knots.shape[0] == 1:
            return base
        return base + self.slopes[:, idx] * (tc - self.knots[idx])

    def at(self, t: torch.Tensor) -> torch.Tensor:
        """Values at many times ``t (T,)``: ``(T, B, n)``."""
        if self.values.shape[-1] == 0:
            return self.values[:, :1, :].expand(-1, t.shape[0], -1).transpose(0, 1)
        idx, tc = self._index(t)
        base = self.values[:, idx]  # (B, T, n)
        if self.knots.shape[0] > 1:
            base = base + self.slopes[:, idx] * (tc - self.knots[idx])[None, :, None]
        return base.transpose(0, 1)

    def at_each(self, t: torch.Tensor) -> torch.Tensor:
        """Values of each batch element at its own times ``t (T, B)``: ``(T, B, n)`` (memory T·B·n,
        where :meth:`at` on the flattened times would take T·B²·n)."""
        B = self.values.shape[0]
        if t.ndim != 2 or t.shape[1] != B:
            raise ValueError(f"at_each needs times (T, {B}), one column per batch element, but got {tuple(t.shape)}")
        if self.values.shape[-1] == 0:
            return self.values[:, :1, :].expand(-1, t.shape[0], -1).transpose(0, 1)
        idx, tc = self._index(t)  # (T, B)
        rows = torch.arange(B)[None, :].expand_as(idx)
        base = self.values[rows, idx]  # (T, B, n)
        if self.knots.shape[0] > 1:
            base = base + self.slopes[rows, idx] * (tc - self.knots[idx])[..., None]
        return base

    def each(self, t: torch.Tensor) -> torch.Tensor:
        """Each batch element at its own time ``t (B,)`` (s): ``(B, n)`` (a solver with a clock per
        element, :mod:`physmend.simulate.clocks`)."""
        B, K = self.values.shape[0], len(self._knot_list)
        if t.shape != (B,) or t.requires_grad or K < 2 or self.values.shape[-1] == 0:
            return self.at_each(t[None])[0]
        tc = t.clamp(self._knot_list[0], self._knot_list[-1])
        i = (torch.searchsorted(self.knots, tc, right=True) - 1).clamp_(0, K - 2)
        rows = self._rows if self._rows.shape[0] == B else torch.arange(B)
        return torch.addcmul(self.values[rows, i], self.slopes[rows, i], (tc - self.knots[i])[:, None])

    def kinks(self) -> list[torch.Tensor]:
        """Per batch element, the knots (s) where its own interpolant bends: ``B`` tensors.

        The knots are shared by the batch (the union of every element's sample times); a knot that
        is not one of an element's own samples lies on a straight piece of its interpolant (equal
        slopes on both sides, to rounding), so a solver need not end a step there.
        """
        B = self.values.shape[0]
        if self.knots.shape[0] < 3 or self.values.shape[-1] == 0:
            return [self.knots[1:-1].clone() for _ in range(B)]
        jump = (self.slopes[:, 1:] - self.slopes[:, :-1]).abs()  # (B, K-2, n): at inner knots
        scale = self.slopes.abs().amax(1, keepdim=True)  # (B, 1, n)
        bends = (jump > 1e-9 * scale).any(-1)  # (B, K-2)
        inner = self.knots[1:-1]
        return [inner[bends[b]] for b in range(B)]

    def select(self, index: Sequence[int] | torch.Tensor) -> "PiecewiseLinear":
        """The same inputs for a subset (or repetition) of batch elements."""
        idx = torch.as_tensor(index, dtype=torch.long)
        return PiecewiseLinear(self.knots, self.values[idx])


def union_knots(series: Sequence[Sequence[np.ndarray]]) -> np.ndarray:
    """Sorted union of all sample times (s) of all channels of all batch elements."""
    times = [np.asarray(t, dtype=np.float64) for per in series for t in per]
    return np.unique(np.concatenate(times)) if times else np.zeros(1)


def from_channels(
    channels: Sequence[Sequence[tuple[np.ndarray, np.ndarray]]], dtype: torch.dtype = torch.float64
) -> PiecewiseLinear:
    """Build batched inputs from ``channels[b][i] = (time (n,), values (n,))`` of batch element b, input i.

    The knots are the union of all sample times, so each channel's own linear interpolant is
    reproduced exactly.
    """
    n_inputs = len(channels[0]) if channels else 0
    if n_inputs == 0:
        return PiecewiseLinear(torch.zeros(1, dtype=dtype), torch.zeros(len(channels), 1, 0, dtype=dtype))
    knots = union_knots([[c[0] for c in per] for per in channels])
    vals = np.empty((len(channels), knots.size, n_inputs))
    for b, per in enumerate(channels):
        for i, (t, v) in enumerate(per):
            vals[b, :, i] = np.interp(knots, t, v)
    return PiecewiseLinear(torch.as_tensor(knots, dtype=dtype), torch.as_tensor(vals, dtype=dtype))
