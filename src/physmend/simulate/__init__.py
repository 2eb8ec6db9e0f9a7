"""Batched differentiable simulation: solvers, inputs, experiment batches."""

from __future__ import annotations

from physmend.simulate.batch import Batch, Trajectories, make_batch, simulate_batch
from physmend.simulate.core import available_methods, odeint
from physmend.simulate.errors import SimulationError
from physmend.simulate.inputs import PiecewiseLinear, from_channels

__all__ = [
    "Batch",
    "PiecewiseLinear",
    "SimulationError",
    "Trajectories",
    "available_methods",
    "from_channels",
    "make_batch",
    "odeint",
    "simulate_batch",
]
