"""Synthetic telemetry of an outdoor telecom cabinet — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real cabinet follows the engineer's model (``model.py``, with the
declared wall conductance walls.UA = 8 W/K) plus **stack-effect ventilation** through two louvres
(top and bottom of the door) that the model leaves out. Warm air leaves at the top and outdoor
air enters at the bottom, driven by buoyancy: the air flow grows with √ΔT and carries ΔT, so the
heat it removes from the cabinet air is

    cabinet.air.C·der(cabinet.air.T) = equipment.Q_flow − walls.Q_flow
                                       − 1.6·(cabinet.air.T − outdoor.T)·√|cabinet.air.T − outdoor.T|   (W)
                                         ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^ concealed

(``1.6 W/K^1.5 ≈ ρ·c_p·C_d·A·√(2·g·H/T_mean)``: louvres of A = 100 cm², C_d = 0.6, H = 0.8 m
between them, T_mean ≈ 303 K held fixed). It grows with the same temperature difference the
uncertain walls.UA multiplies, so an estimated UA can absorb part of it. Temperatures are in °C:
the term depends on the difference only, never on where the scale's zero is.

The logger: rows every 60 s over 24 h; the chassis and the cabinet air each read by a sensor with
σ = 0.2 K and 0.1 K resolution, a few readings missing; the electronics' power (1 W resolution)
and the outdoor temperature (0.1 K) logged on the same rows. Power: a base load that follows the
day's traffic, with units (radios, rectifier modules) switching on and off in steps.

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
C_VENT = 1.6  # W/K^1.5 (concealed)
C_EQ, G_EQ, C_AIR, UA = 3.0e4, 25.0, 1.5e4, 8.0  # as in model.py (UA: its declared value is the true one)
DT, DURATION = 60.0, 24 * 3600.0  # s
NOISE, RESOLUTION = 0.2, 0.1  # K
# id, role, (outdoor mean, daily amplitude) degC, mean power W, start (equipment.T, cabinet.air.T) degC, seed
EXPERIMENTS = [
    ("w1", "train", (-4.0, 4.0), 260.0, (18.0, 8.0), 21),      # a winter day
    ("w2", "train", (12.0, 6.0), 200.0, (30.0, 22.0), 22),     # spring
    ("w3", "train", (7.0, 3.0), 320.0, (25.0, 12.0), 23),      # a grey autumn day
    ("w4", "validation", (16.0, 5.0), 240.0, (34.0, 25.0), 24),
    ("w5", "test", (31.0, 6.0), 300.0, (52.0, 41.0), 25),      # a summer heat wave: warmer than any training day
]


def ventilation(T_air: np.ndarray, T_out: np.ndarray) -> np.ndarray:
    """The concealed term of ``cabinet.air.C·der(cabinet.air.T) = …`` (W)."""
    dT = np.asarray(T_air) - np.asarray(T_out)
    return -C_VENT * dT * np.sqrt(np.abs(dT))


def outdoor(t: np.ndarray, mean: float, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """Outdoor temperature on the logged rows (degC): a daily cycle (coldest near 5 h) and weather."""
    day = t / 86400.0
    weather = np.cumsum(rng.normal(0.0, 0.04, t.size))
    return np.round(mean - amplitude * np.cos(2 * np.pi * (day - 5 / 24)) + weather, 1)


def power(t: np.ndarray, mean: float, rng: np.random.Generator) -> np.ndarray:
    """Electrical power of the electronics on the logged rows (W): daily traffic plus units switching."""
    hour = t / 3600.0
    traffic = 1.0 + 0.25 * np.sin(2 * np.pi * (hour - 9.0) / 24.0)
    steps = np.zeros_like(t)
    k = 0
    while k < t.size:  # a unit of 20-70 W switched on or off, held 40 min to 3 h
        n = int(rng.integers(40, 180))
        steps[k:k + n] = rng.choice([-1.0, 0.0, 1.0]) * rng.uniform(20.0, 70.0)
        k += n
    ripple = rng.normal(0.0, 3.0, t.size)
    return np.round(np.clip(mean * traffic + steps + ripple, 50.0, None), 0)


def record(out: tuple[float, float], mean_power: float, start: tuple[float, float], seed: int
           ) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION + DT / 2, DT)
    T_out = outdoor(t, *out, rng)
    P = power(t, mean_power, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        T_eq, T_air = y
        p, to = np.interp(tt, t, P), np.interp(tt, t, T_out)
        q_eq = G_EQ * (T_eq - T_air)
        return [(p - q_eq) / C_EQ, (q_eq - UA * (T_air - to) + ventilation(T_air, to)) / C_AIR]

    sol = solve_ivp(rhs, (0.0, DURATION), list(start), t_eval=t, method="LSODA", rtol=1e-10, atol=1e-10,
                    max_step=DT / 2)
    assert sol.success, sol.message
    T_eq, T_air = sol.y
    columns = {}
    for name, true in (("equipment.T", T_eq), ("cabinet.air.T", T_air)):
        measured = np.round((true + rng.normal(0.0, NOISE, t.size)) / RESOLUTION) * RESOLUTION
        measured[rng.choice(np.arange(10, t.size - 10), size=4, replace=False)] = np.nan
        columns[name] = measured
    telemetry = pd.DataFrame({"time": t, **columns, "equipment.P": P, "outdoor.T": T_out})
    truth = pd.DataFrame({"time": t, "equipment.T": T_eq, "cabinet.air.T": T_air, "equipment.P": P,
                          "outdoor.T": T_out, "term:cabinet.air.T": ventilation(T_air, T_out)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, out, mean_power, start, seed in EXPERIMENTS:
        telemetry, truth = record(out, mean_power, start, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        dT = truth["cabinet.air.T"] - truth["outdoor.T"]
        vent, walls = -truth["term:cabinet.air.T"], UA * dT
        print(f"{exp_id} ({role}): {len(telemetry)} rows, outdoor {truth['outdoor.T'].min():.1f}..{truth['outdoor.T'].max():.1f} degC, "
              f"air {truth['cabinet.air.T'].min():.1f}..{truth['cabinet.air.T'].max():.1f}, "
              f"equipment {truth['equipment.T'].min():.1f}..{truth['equipment.T'].max():.1f}, "
              f"air-outdoor {dT.min():.1f}..{dT.max():.1f} K, power {truth['equipment.P'].min():.0f}..{truth['equipment.P'].max():.0f} W, "
              f"ventilation {vent.min():.0f}..{vent.max():.0f} W (walls {walls.min():.0f}..{walls.max():.0f} W)")


if __name__ == "__main__":
    main()
