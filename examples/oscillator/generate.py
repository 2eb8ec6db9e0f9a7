"""Synthetic telemetry of the shaker rig — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real rig is the engineer's model (``model.py``) plus **Coulomb
friction** on the mass, ``-F_c·sign(v)`` with ``F_c = 0.6 N`` (a non-smooth term on the equation
of the unmeasured velocity). Position is logged every 10 ms with 0.5 mm noise, quantised to 0.1 mm;
the shaker force (the model's input) is logged on the same rows.

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
F_C = 0.6  # N, Coulomb friction (concealed)
K, C = 40.0, 0.8  # N/m, N.s/m (as the engineer has them)
DT, DURATION = 0.01, 15.0  # s
NOISE, RESOLUTION = 5e-4, 1e-4  # m
EXPERIMENTS = [  # id, role, mass (kg), forcing amplitude (N), seed
    ("a", "train", 0.8, 4.0, 1), ("b", "train", 1.0, 6.0, 2), ("c", "train", 1.3, 5.0, 3),
    ("d", "validation", 1.1, 5.5, 4), ("e", "test", 1.6, 7.0, 5),
]


def forcing(t: np.ndarray, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """Shaker force: a few sines of random frequency and phase plus steps (N)."""
    f = np.zeros_like(t)
    for _ in range(3):
        f += amplitude / 3 * np.sin(2 * np.pi * rng.uniform(0.2, 1.5) * t + rng.uniform(0, 2 * np.pi))
    steps = np.cumsum(rng.normal(0, amplitude / 4, size=6))
    return f + steps[np.minimum((t / DURATION * 6).astype(int), 5)]


def friction(v: np.ndarray | float) -> np.ndarray | float:
    """The concealed term added to ``m·der(v) = …`` (N)."""
    return -F_C * np.tanh(np.asarray(v) / 1e-3)  # sign(v), smoothed over 1 mm/s for the integrator


def record(mass: float, amplitude: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(0.0, DURATION + DT / 2, DT), 6)
    force = np.round(forcing(t, amplitude, rng), 3)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        x, v = y
        f = np.interp(tt, t, force)  # the input as the model sees it: linear between logged samples
        return [v, (f - K * x - C * v + friction(v)) / mass]

    sol = solve_ivp(rhs, (0.0, DURATION), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-11, max_step=DT)
    assert sol.success, sol.message
    x, v = sol.y
    measured = np.round((x + rng.normal(0, NOISE, x.size)) / RESOLUTION) * RESOLUTION
    gap = rng.integers(200, t.size - 200)
    measured[gap:gap + 30] = np.nan  # a sensor dropout of 0.3 s
    telemetry = pd.DataFrame({"time": t, "mass.x": measured, "shaker.F": force})
    truth = pd.DataFrame({"time": t, "mass.x": x, "mass.v": v, "shaker.F": force, "term:mass.v": friction(v)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, mass, amplitude, seed in EXPERIMENTS:
        telemetry, truth = record(mass, amplitude, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} rows")


if __name__ == "__main__":
    main()
