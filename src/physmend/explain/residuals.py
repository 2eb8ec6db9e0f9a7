"""Residual analysis of a simulation against telemetry: error sizes, worst windows, correlates.

All functions take plain numpy arrays: ``t (T,)`` seconds, ``measured``/``simulated`` ``(T,)`` in the
output's unit with NaN where not measured.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class ErrorStats:
    """RMSE, bias (mean of simulated − measured) and an estimate of the sensor noise (output units)."""

    rmse: float
    bias: float
    max_abs: float
    noise: float
    n: int

    @property
    def ratio(self) -> float:
        """RMSE in multiples of the estimated sensor noise."""
        return self.rmse / self.noise if self.noise > 0 else float("inf")

    def as_dict(self) -> dict[str, float]:
        return {**asdict(self), "ratio_to_noise": self.ratio}


def noise_floor(t: np.ndarray, measured: np.ndarray) -> float:
    """Sensor-noise standard deviation estimated from second differences of the measurements.

    For white noise of standard deviation σ on a smooth signal, ``y[i+1] - 2 y[i] + y[i-1]`` has
    standard deviation ``σ √6``; a median absolute deviation keeps gaps and steps from inflating it.
    """
    ok = np.isfinite(measured)
    y = measured[ok]
    if y.size < 5:
        return float("nan")
    d2 = y[2:] - 2 * y[1:-1] + y[:-2]
    mad = np.median(np.abs(d2 - np.median(d2)))
    sigma = 1.4826 * mad / np.sqrt(6.0)
    if sigma == 0:  # quantised, nearly constant records: fall back to the standard deviation
        sigma = float(np.std(d2) / np.sqrt(6.0))
    return float(sigma)


def error_stats(t: np.ndarray, measured: np.ndarray, simulated: np.ndarray) -> ErrorStats:
    ok = np.isfinite(measured) & np.isfinite(simulated)
    r = simulated[ok] - measured[ok]
    if r.size == 0:
        return ErrorStats(float("nan"), float("nan"), float("nan"), float("nan"), 0)
    return ErrorStats(
        rmse=float(np.sqrt(np.mean(r**2))),
        bias=float(np.mean(r)),
        max_abs=float(np.max(np.abs(r))),
        noise=noise_floor(t, measured),
        n=int(r.size),
    )


@dataclass
class Window:
    """A time window (s from the experiment start) and the residual RMS and bias in it."""

    start: float
    end: float
    rms: float
    bias: float


def worst_windows(t: np.ndarray, residual: np.ndarray, *, length: float, count: int) -> list[Window]:
    """The ``count`` non-overlapping windows of duration ``length`` (s) with the largest residual RMS."""
    ok = np.isfinite(residual)
    tt, rr = t[ok], residual[ok]
    if tt.size == 0:
        return []
    full = tt <= tt[-1] - length  # only windows that fit inside the record
    if not full.any():
        full = tt == tt[0]
    idx0 = np.nonzero(full)[0]
    starts = tt[idx0]
    ends = np.searchsorted(tt, starts + length, side="right")
    c1 = np.concatenate([[0.0], np.cumsum(rr)])
    c2 = np.concatenate([[0.0], np.cumsum(rr**2)])
    n = ends - idx0
    rms = np.sqrt((c2[ends] - c2[idx0]) / np.maximum(n, 1))
    mean = (c1[ends] - c1[idx0]) / np.maximum(n, 1)
    order = np.argsort(-rms)
    chosen: list[Window] = []
    for i in order:
        s, e = float(starts[i]), float(starts[i] + length)
        e = min(e, float(tt[-1]))
        if any(s < w.end and e > w.start for w in chosen):
            continue
        chosen.append(Window(s, e, float(rms[i]), float(mean[i])))
        if len(chosen) == count:
            break
    return chosen


def moving_average(y: np.ndarray, samples: int) -> np.ndarray:
    """Centered moving average over finite samples (NaN stay NaN)."""
    if samples <= 1:
        return y.copy()
    ok = np.isfinite(y)
    filled = np.where(ok, y, 0.0)
    kernel = np.ones(samples)
    num = np.convolve(filled, kernel, mode="same")
    den = np.convolve(ok.astype(float), kernel, mode="same")
    out = num / np.maximum(den, 1e-300)
    out[~ok] = np.nan
    return out


def residual_rate(t: np.ndarray, residual: np.ndarray, smooth_samples: int) -> np.ndarray:
    """Time derivative (units/s) of the smoothed residual: how fast the model drifts from the data.

    For a missing term acting on a measured state, this rate is roughly that term divided by the
    state's capacity, so it correlates with the variables the missing physics depends on.
    """
    sm = moving_average(residual, smooth_samples)
    ok = np.isfinite(sm)
    rate = np.full_like(sm, np.nan)
    if ok.sum() >= 3:
        rate[ok] = np.gradient(sm[ok], t[ok])
    return rate


@dataclass
class Correlate:
    """A model variable or input and its Pearson correlation with a residual signal."""

    name: str
    kind: str
    r: float


def correlates(
    signal: np.ndarray, candidates: dict[str, tuple[str, np.ndarray]], count: int
) -> list[Correlate]:
    """Rank ``candidates`` (name -> (kind, values like ``signal``)) by |Pearson r| with ``signal``."""
    ok = np.isfinite(signal)
    out: list[Correlate] = []
    for name, (kind, values) in candidates.items():
        m = ok & np.isfinite(values)
        if m.sum() < 3:
            continue
        a, b = signal[m], values[m]
        sa, sb = a.std(), b.std()
        if sa == 0 or sb < 1e-12 * max(1.0, np.abs(b).max()):
            continue
        r = float(np.mean((a - a.mean()) * (b - b.mean())) / (sa * sb))
        out.append(Correlate(name, kind, r))
    out.sort(key=lambda c: -abs(c.r))
    return out[:count]
