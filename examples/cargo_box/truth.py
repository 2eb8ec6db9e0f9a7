"""The concealed truth: the cargo box as it really behaves, used ONLY to generate telemetry.

The real box is the engineer's model (``build_model`` in ``model.py``)
plus one effect that model leaves out: **buoyancy-driven air leakage through gaps in the
bulkhead**. Cold, dense air from the colder zone flows out low through the gaps while warm air
flows in high; the exchanged volume flow grows with ``sqrt(|ΔT|)`` (buoyancy head), so the heat
carried between the two air volumes is

    Q_leak = c · ΔT · sqrt(|ΔT|)     [W],   ΔT = zone1.air.T − zone2.air.T  [K],

flowing from zone 1 to zone 2 (negative when zone 1 is colder). With ``c =``
:data:`LEAK_COEFFICIENT` = 1.0 W/K^1.5, ``Q_leak ≈ 89 W`` at ΔT = 20 K, ``≈ 156 W`` at 29 K and
``≈ 250 W`` at 40 K (during pull-downs) — 1.7–2× the conduction through the bulkhead with its
films (≈ 2.7 W/K at the default inside convection: ≈ 54 W at 20 K, ≈ 78 W at 29 K). In the
shipped experiments the leak settles at about −90 W (ID 1), −155 W (ID 2) and −103 W (ID 3)
during regulation, peaking at up to −255 W during the pull-down.

Nothing in the physmend pipeline imports this module; tests import it only to check what the
pipeline found against the truth.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from model import T_UNIT, build_model
from physmend.modeling import Model
from physmend.modeling import thermal as th

LEAK_COEFFICIENT = 1.0
"""c in ``Q = c·ΔT·sqrt(|ΔT|)``, W/K^1.5 (orifice-like buoyant exchange through bulkhead gaps)."""


def true_leakage(T1: np.ndarray, T2: np.ndarray) -> np.ndarray:
    """Concealed heat flow from zone 1 air to zone 2 air (W) for air temperatures in degC.

    ``T1``, ``T2``: arrays of the same shape (or broadcastable); returns that shape.
    """
    dT = np.asarray(T1, dtype=float) - np.asarray(T2, dtype=float)
    return LEAK_COEFFICIENT * dT * np.sqrt(np.abs(dT))


def buoyant_exchange(m: Model, name: str, coefficient: float | sp.Expr, *, T_unit: str = T_UNIT) -> th.Component:
    """Nonlinear conductor: ``Q = c·(a.T − b.T)·sqrt(|a.T − b.T|)`` (W) from port a to port b."""
    a = th.heat_port(m, f"{name}.a", name, T_unit)
    b = th.heat_port(m, f"{name}.b", name, T_unit)
    Q = m.variable(f"{name}.Q_flow", unit="W", description=f"heat carried by air exchange through {name}, a to b")
    dT = a.T - b.T
    m.equation(Q, coefficient * dT * sp.sqrt(sp.Abs(dT)), owner=name, label=f"{name}: buoyant air exchange")
    m.equation(a.Q_flow, Q, owner=name, label=f"{name}: flow in at a")
    m.equation(b.Q_flow, -Q, owner=name, label=f"{name}: flow out at b")
    return th.Component(name, {"a": a, "b": b}, {"Q_flow": Q})


def build_truth_model() -> Model:
    """The engineer's model plus the bulkhead leakage ``bulkhead.leak`` (same states, inputs, outputs)."""
    m = build_model()
    m.name = "cargo_box_truth"
    leak = buoyant_exchange(m, "bulkhead.leak", LEAK_COEFFICIENT)
    m.connect(m.connectors["zone1.air.port"], leak.a)
    m.connect(leak.b, m.connectors["zone2.air.port"])
    return m
