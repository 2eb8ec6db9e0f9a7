"""Synthetic telemetry of greenhouses over several days — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real houses follow the engineer's model (``model.py``) plus the
**solar gain** through the glazing, ``tau·glazing.area·sun.I`` W with ``tau = 0.6``, on the zone's
heat balance (an input scaled by a parameter that differs between houses). Rows every 5 min over
4 days; zone temperature noise 0.15 K (0.1 K resolution); a thermostat switches the heater.

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
TAU = 0.6  # transmittance x absorptance (concealed)
C, UA = 4.0e6, 600.0
DT, DAYS = 300.0, 4
NOISE, RESOLUTION = 0.15, 0.1
EXPERIMENTS = [  # id, role, glazing area (m2), setpoint (degC), seed
    ("g1", "train", 3.0, 16.0, 1), ("g2", "train", 6.0, 18.0, 2), ("g3", "train", 9.0, 15.0, 3),
    ("g4", "validation", 7.5, 17.0, 4), ("g5", "test", 12.0, 16.0, 5),
]


def weather(t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    day = t / 86400.0
    outdoor = 8 + 5 * np.sin(2 * np.pi * (day - 0.35)) + np.cumsum(rng.normal(0, 0.05, t.size))
    clear = np.clip(np.sin(2 * np.pi * (day - 0.25)), 0, None) * 700
    clouds = np.clip(1 - 0.6 * np.abs(np.convolve(rng.normal(0, 1, t.size), np.ones(12) / 12, "same")), 0.2, 1)
    return np.round(outdoor, 1), np.round(clear * clouds, 0)


def gain(area: float, irradiance: np.ndarray) -> np.ndarray:
    """The concealed term of ``zone.C·der(zone.T) = …`` (W)."""
    return TAU * area * irradiance


def record(area: float, setpoint: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DAYS * 86400.0 + DT / 2, DT)
    outdoor, sun = weather(t, rng)
    heater = np.zeros_like(t)
    T = np.empty_like(t)
    T[0] = setpoint
    for k in range(t.size - 1):  # thermostat on the logged temperature, decides the next interval's power
        measured = T[k] + rng.normal(0, NOISE)
        heater[k + 1] = 6000.0 if measured < setpoint - 0.5 else (0.0 if measured > setpoint + 0.5 else heater[k])
        seg = t[k:k + 2]

        def rhs(tt: float, y: np.ndarray) -> list[float]:
            To, I, P = (np.interp(tt, seg, v[k:k + 2]) for v in (outdoor, sun, heater))
            return [(P - UA * (y[0] - To) + gain(area, I)) / C]

        sol = solve_ivp(rhs, (seg[0], seg[1]), [T[k]], rtol=1e-10, atol=1e-10)
        T[k + 1] = sol.y[0, -1]
    measured = np.round((T + rng.normal(0, NOISE, T.size)) / RESOLUTION) * RESOLUTION
    gap = rng.integers(100, t.size - 100)
    measured[gap:gap + 12] = np.nan  # an hour without the sensor
    telemetry = pd.DataFrame({"time": t, "zone.T": measured, "outdoor.T": outdoor, "sun.I": sun, "heater.P": heater})
    truth = pd.DataFrame({"time": t, "zone.T": T, "outdoor.T": outdoor, "sun.I": sun, "heater.P": heater,
                          "term:zone.T": gain(area, sun)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, area, setpoint, seed in EXPERIMENTS:
        telemetry, truth = record(area, setpoint, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} rows")


if __name__ == "__main__":
    main()
