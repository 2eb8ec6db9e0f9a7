"""Synthetic telemetry of a laboratory furnace — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real furnace follows the engineer's model (``model.py``, with the
declared insulation conductance UA = 20 W/K) plus **thermal radiation** from the hot door and
viewport to the room, ``-eps_sigma_A·(chamber.T^4 - room.T^4)`` W with ``eps_sigma_A = 4.54e-9
W/K^4`` — a loss that grows with the same temperature difference UA multiplies, so an estimated
UA can absorb much of it. Rows every 30 s over 3 h; temperature noise 0.5 K (0.1 K resolution).

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
EPS_SIGMA_A = 0.8 * 5.670e-8 * 0.1  # emissivity x Stefan-Boltzmann x area (concealed), W/K^4
C, UA = 5.0e4, 20.0
DT, DURATION = 30.0, 3 * 3600.0
NOISE, RESOLUTION = 0.5, 0.1
EXPERIMENTS = [  # id, role, power levels of the program (W), seed
    ("p1", "train", (2000, 4500, 3000), 1), ("p2", "train", (3500, 1500, 5000), 2),
    ("p3", "train", (2500, 5500, 4000), 3), ("p4", "validation", (3000, 5000, 2000), 4),
    ("p5", "test", (6000, 7000, 4500), 5),
]


def radiation(T: np.ndarray, T_room: np.ndarray) -> np.ndarray:
    """The concealed term of ``chamber.C·der(chamber.T) = …`` (W)."""
    return -EPS_SIGMA_A * (np.asarray(T) ** 4 - np.asarray(T_room) ** 4)


def record(levels: tuple[float, ...], seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION + DT / 2, DT)
    stage = np.minimum((t / DURATION * len(levels)).astype(int), len(levels) - 1)
    power = np.round(np.asarray(levels, float)[stage] * (1 + 0.05 * np.sin(t / 600.0 + seed)), 0)
    room = np.round(295 + 2 * np.sin(t / 5000.0 + seed) + np.cumsum(rng.normal(0, 0.02, t.size)), 1)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        P, Tr = np.interp(tt, t, power), np.interp(tt, t, room)
        return [(P - UA * (y[0] - Tr) + radiation(y[0], Tr)) / C]

    sol = solve_ivp(rhs, (0.0, DURATION), [295.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-8, max_step=DT)
    assert sol.success, sol.message
    T = sol.y[0]
    measured = np.round((T + rng.normal(0, NOISE, T.size)) / RESOLUTION) * RESOLUTION
    measured[rng.integers(20, t.size - 20, size=3)] = np.nan  # a few rows lost
    telemetry = pd.DataFrame({"time": t, "chamber.T": measured, "heater.P": power, "room.T": room})
    truth = pd.DataFrame({"time": t, "chamber.T": T, "heater.P": power, "room.T": room,
                          "term:chamber.T": radiation(T, room)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, levels, seed in EXPERIMENTS:
        telemetry, truth = record(levels, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} rows, up to {truth['chamber.T'].max():.0f} K")


if __name__ == "__main__":
    main()
