"""Data that no simulation or fit can use, named before any work starts.

Two general rules, each derived from what the arithmetic or the solver can do, not tuned to a record:

* **Magnitude.** Every fit, error, variance and RMSE physmend computes sums squares of a column's
  values; in the arithmetic of the model (``simulate.dtype``: float64 unless set) that sum must stay
  finite, so each value must satisfy ``|v| ≤ sqrt(max / n)`` for a column of ``n`` values (about
  1e151 for a million float64 values). A value beyond it (``1e300``) is a sensor fault or a wrong unit,
  and would otherwise end as ``inf``/``nan`` in every result.
* **Sampling.** A simulation ends a solver step on every input sample of an experiment (and, with a
  solver that keeps each experiment on its own clock — ``rodas*`` — on every measured row): an
  experiment with more such times than the solver's step budget (``simulate.options.max_steps``,
  :data:`STEP_BUDGET` unless set) cannot be simulated at all, and would fail only after minutes. The
  message says how finely the record is sampled against the model's fastest time constant and how to
  resample it.

Each failure is one :class:`DataError` line naming the experiment, file and column, the rule and the
value, in the data's own time unit.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from physmend.data.errors import DataError
from physmend.data.telemetry import Channel
from physmend.settings import SimulateSettings

#: physmend's solvers stop after this many steps unless ``simulate.options.max_steps`` says otherwise
STEP_BUDGET = 100_000
#: solvers that end a step on every measured row of an experiment (each experiment on its own clock)
ROW_CLOCK_METHODS = ("rodas3", "rodas4", "rodas4p2")
#: solvers that count their steps against ``max_steps`` (torchdiffeq's methods have no such budget)
BUDGETED_METHODS = ("rosenbrock23", *ROW_CLOCK_METHODS)


def largest_magnitude(n: int, dtype: Any = np.float64) -> float:
    """The largest ``|v|`` whose square, summed over ``n`` values, stays finite in ``dtype``."""
    return math.sqrt(float(np.finfo(dtype).max) / max(int(n), 1))


def check_magnitude(values: np.ndarray, *, where: str, label: str, row: Callable[[int], str],
                    dtype: Any = np.float64) -> None:
    """Raise :class:`DataError` when a finite value of ``values`` is beyond :func:`largest_magnitude`.

    ``label`` names the column (``column 'x' (model output 'prey.x')``); ``row(i)`` names row ``i``."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return
    bound = largest_magnitude(values.size, dtype)
    big = np.flatnonzero(np.abs(values) > bound)
    if big.size:
        i = int(big[0])
        name = np.dtype(dtype).name
        raise DataError(
            f"{where}: {label} holds {float(values[i]):.6g} at {row(i)}: beyond {name} arithmetic (the squares of its "
            f"{values.size} values must sum to a finite number: |value| ≤ {bound:.3g}); fix or drop the faulty rows, "
            "or use a larger unit")


def solver_stops(obs_time: np.ndarray, input_times: Sequence[np.ndarray], method: str) -> int:
    """How many times a simulation of one experiment must end a solver step on (see the module
    docstring): its input samples inside the record, with its measured rows for :data:`ROW_CLOCK_METHODS`."""
    end = float(obs_time[-1])
    parts = [t[(t > 0) & (t < end)] for t in input_times]
    if method in ROW_CLOCK_METHODS:
        parts.append(obs_time)
    return int(np.unique(np.concatenate(parts)).size) if parts else 0


def record_starts(experiments: Sequence[Any]) -> list[Any]:
    """Each experiment cut to its first two measured rows and the input samples that cover them:
    enough for the model's time constant at the records' starts, without a grid of every row."""
    out = []
    for e in experiments:
        if len(e.obs_time) < 2:
            out.append(e)
            continue
        end = float(e.obs_time[1])
        inputs = {}
        for name, c in e.inputs.items():
            k = int(np.searchsorted(c.time, end, side="right")) + 1
            inputs[name] = Channel(time=c.time[:k], values=c.values[:k])
        out.append(dataclasses.replace(e, obs_time=e.obs_time[:2], obs=e.obs[:2], inputs=inputs, split_time=None))
    return out


def check_sampling(experiments: Sequence[Any], simulate_cfg: Any, *, time_unit: str,
                   fastest: Callable[[], float] | None = None) -> None:
    """Raise :class:`DataError` when an experiment has more solver stops than the step budget.

    ``experiments``: loaded :class:`~physmend.data.Experiment` objects; ``simulate_cfg``: the
    ``simulate`` group (``method``, ``options.max_steps``); ``fastest()``: the model's fastest
    time constant in ``time_unit`` (called only to word the error)."""
    simulate = SimulateSettings.build(simulate_cfg)  # checked; missing keys: conf/simulate/default.yaml
    method = simulate.method
    if method not in BUDGETED_METHODS:
        return
    budget = int(dict(simulate.options or {}).get("max_steps", STEP_BUDGET))
    for e in experiments:
        stops = solver_stops(np.asarray(e.obs_time), [np.asarray(c.time) for c in e.inputs.values()], method)
        if stops <= budget:
            continue
        gaps = np.diff(np.asarray(e.obs_time))
        step = float(np.median(gaps)) if gaps.size else float(e.t_end)
        keep = math.ceil(stops / (budget / 2))  # every keep-th row: half the budget, room for the solver's own steps
        why = ""
        if fastest is not None:
            try:
                tau = float(fastest())
            except Exception:  # noqa: BLE001 - the time constant only words the message
                tau = math.inf
            if math.isfinite(tau) and tau > 0:
                why = f" ({tau / step:.3g} per the model's fastest time constant, {tau:.3g} {time_unit})"
        raise DataError(
            f"experiment {e.id!r} (file {e.file.name}): {len(e.obs_time)} rows, one every {step:.3g} {time_unit}{why}: "
            f"the solver would stop {stops} times (at most {budget}: simulate.options.max_steps); "
            f"resample (e.g. 1 row in {keep}: every {step * keep:.3g} {time_unit}) or split it")
