"""Synthetic telemetry of a two-tank rig — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real rig follows the engineer's model (``model.py``) plus a **leak
out of the upper tank** through a crack near its bottom, ``-c·sqrt(tank1.h)`` m³/s with
``c = 0.0012 m^2.5/s``, on the equation of the upper tank, whose level is not measured and whose
starting level is unknown. Rows every 10 s over 1 h; lower-tank level noise 2 mm (1 mm resolution).

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
C_LEAK = 0.0012  # m^2.5/s (concealed)
A1 = A2 = 0.5
K1 = 0.004
DT, DURATION = 10.0, 3600.0
NOISE, RESOLUTION = 0.002, 0.001
EXPERIMENTS = [  # id, role, valve setting k2, start levels (h1, h2), mean pump flow (m3/s), seed
    ("t1", "train", 0.003, (0.20, 0.25), 0.0020, 1), ("t2", "train", 0.004, (0.40, 0.15), 0.0022, 2),
    ("t3", "train", 0.005, (0.30, 0.35), 0.0025, 3), ("t4", "validation", 0.0045, (0.25, 0.30), 0.0023, 4),
    ("t5", "test", 0.006, (0.50, 0.20), 0.0032, 5),
]


def leak(h1: np.ndarray) -> np.ndarray:
    """The concealed term of ``tank1.A·der(tank1.h) = …`` (m³/s)."""
    return -C_LEAK * np.sqrt(np.clip(h1, 0, None))


def pump(t: np.ndarray, mean: float, rng: np.random.Generator) -> np.ndarray:
    out = np.zeros_like(t)
    k = 0
    while k < t.size:
        n = int(rng.integers(18, 60))
        out[k:k + n] = rng.uniform(0.3, 1.7) * mean
        k += n
    return np.round(out, 5)


def record(k2: float, h0: tuple[float, float], mean: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION + DT / 2, DT)
    q = pump(t, mean, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        h1, h2 = np.clip(y, 0, None)
        q12 = K1 * np.sqrt(h1)
        return [(np.interp(tt, t, q) - q12 + leak(h1)) / A1, (q12 - k2 * np.sqrt(h2)) / A2]

    sol = solve_ivp(rhs, (0.0, DURATION), list(h0), t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT)
    assert sol.success, sol.message
    h1, h2 = sol.y
    measured = np.round((h2 + rng.normal(0, NOISE, h2.size)) / RESOLUTION) * RESOLUTION
    measured[rng.integers(30, t.size - 30, size=4)] = np.nan
    telemetry = pd.DataFrame({"time": t, "tank2.h": measured, "pump.q": q})
    truth = pd.DataFrame({"time": t, "tank1.h": h1, "tank2.h": h2, "pump.q": q, "term:tank1.h": leak(h1)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, k2, h0, mean, seed in EXPERIMENTS:
        telemetry, truth = record(k2, h0, mean, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} rows, h1 {truth['tank1.h'].min():.2f}..{truth['tank1.h'].max():.2f} m, "
              f"h2 {truth['tank2.h'].min():.2f}..{truth['tank2.h'].max():.2f} m")


if __name__ == "__main__":
    main()
