"""Synthetic telemetry of a two-tank rig — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC. The real rig follows the engineer's model (``model.py``) plus one thing
he left out: a **leak out of the upper tank** through a crack near its bottom, a Torricelli outflow
to the floor,

    tank1.A·der(tank1.h) = pump.q − orifice.k·√tank1.h  − 0.001·√tank1.h      (m³/s)
                                                        ^^^^^^^^^^^^^^^^ concealed

on the equation of the upper tank, whose level is **not measured** and whose starting level is
**unknown**. It shows only through the lower tank: less water arrives, and the upper tank's
response to the pump is faster (its outflow coefficient is effectively 0.005 instead of 0.004).
Why this variant is identifiable from the lower level alone: the best correction on the lower
tank's equation only (any combination of √h1, √h2, h1, h2, pump flow and a constant, with the
upper tank's start re-estimated) still misses the lower level by about 9 mm RMSE over the
training records (σ = 2 mm), because it cannot reproduce the upper tank's faster response when
the pump flow changes; the leak on the upper tank fits to the noise (checked by output-error
least squares on t1–t3; the model as written, its upper start re-estimated, misses by 0.16 m).

The logger: rows every 5 s for 1 h with ±1 s jitter; a few rows lost; the lower level read by a
pressure sensor, σ = 2 mm Gaussian noise and 1 mm resolution, a few readings missing (NaN); the
pump's flow meter logged on the same rows at 0.01 l/s resolution. Pump profiles: random levels
held 2–7 min, reached by a step or a ramp (the tanks never run dry).

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
C_LEAK = 0.001  # m^2.5/s (concealed)
A1, A2 = 0.5, 0.25  # m2: tank1.A, tank2.A (as in model.py)
K1 = 0.004  # m^2.5/s: orifice.k (as in model.py)
DT, DURATION, JITTER = 5.0, 3600.0, 1.0  # s
NOISE, RESOLUTION = 0.002, 0.001  # m: level sensor
FLOW_RESOLUTION = 1e-5  # m3/s (0.01 l/s)
# id, role, valve setting valve.k (m^2.5/s), start levels (tank1.h, tank2.h) in m, mean pump flow (m3/s), seed
EXPERIMENTS = [
    ("t1", "train", 0.003, (0.15, 0.30), 0.0020, 11),
    ("t2", "train", 0.005, (0.45, 0.10), 0.0024, 12),
    ("t3", "train", 0.004, (0.30, 0.50), 0.0028, 13),
    ("t4", "validation", 0.0045, (0.60, 0.25), 0.0026, 14),
    ("t5", "test", 0.004, (0.25, 0.20), 0.0036, 15),  # a pump level not seen in training
]


def leak(h1: np.ndarray) -> np.ndarray:
    """The concealed term of ``tank1.A·der(tank1.h) = …`` (m³/s)."""
    return -C_LEAK * np.sqrt(np.clip(h1, 0, None))


def timestamps(rng: np.random.Generator) -> np.ndarray:
    """Logger rows: nominally every DT, jittered by up to ±JITTER, a few rows lost."""
    t = np.arange(0.0, DURATION + DT / 2, DT)
    t[1:-1] += rng.uniform(-JITTER, JITTER, t.size - 2)
    lost = rng.choice(np.arange(20, t.size - 20), size=5, replace=False)
    return np.round(np.delete(t, lost), 2)


def pump(t: np.ndarray, mean: float, rng: np.random.Generator) -> np.ndarray:
    """Pump flow on the logged rows (m³/s): levels held 2–7 min, reached by a step or a ramp."""
    out = np.empty_like(t)
    level, k = mean, 0
    while k < t.size:
        n = int(rng.integers(24, 84))
        new = rng.uniform(0.5, 1.5) * mean
        ramp = int(rng.integers(6, 24)) if rng.random() < 0.4 else 1
        seg = np.full(n, new)
        seg[:min(ramp, n)] = level + (new - level) * np.arange(1, min(ramp, n) + 1) / ramp
        out[k:k + n] = seg[:t.size - k]
        level, k = new, k + n
    return np.round(out / FLOW_RESOLUTION) * FLOW_RESOLUTION


def record(k2: float, h0: tuple[float, float], mean: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = timestamps(rng)
    q = pump(t, mean, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        h1, h2 = np.clip(y, 0, None)
        q12 = K1 * np.sqrt(h1)
        return [(np.interp(tt, t, q) - q12 + leak(h1)) / A1, (q12 - k2 * np.sqrt(h2)) / A2]

    sol = solve_ivp(rhs, (0.0, t[-1]), list(h0), t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT / 2)
    assert sol.success, sol.message
    h1, h2 = sol.y
    measured = np.round((h2 + rng.normal(0, NOISE, h2.size)) / RESOLUTION) * RESOLUTION
    measured[rng.choice(np.arange(20, t.size - 20), size=6, replace=False)] = np.nan
    telemetry = pd.DataFrame({"time": t, "tank2.h": measured, "pump.q": q})
    truth = pd.DataFrame({"time": t, "tank1.h": h1, "tank2.h": h2, "pump.q": q, "term:tank1.h": leak(h1)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, k2, h0, mean, seed in EXPERIMENTS:
        telemetry, truth = record(k2, h0, mean, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"{exp_id} ({role}): {len(telemetry)} rows, tank1.h {truth['tank1.h'].min():.2f}..{truth['tank1.h'].max():.2f} m, "
              f"tank2.h {truth['tank2.h'].min():.2f}..{truth['tank2.h'].max():.2f} m, "
              f"pump {1000 * telemetry['pump.q'].max():.2f} l/s max, leak up to {-1000 * truth['term:tank1.h'].min():.2f} l/s")


if __name__ == "__main__":
    main()
