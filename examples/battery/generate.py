"""Synthetic telemetry of Li-ion cells under pulsed loads — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real cells follow the engineer's circuit (``model.py``) plus a
**constant parasitic discharge** of 0.25 A (self-discharge through a fault, a constant sink on the
charge balance ``cell.Q·der(cell.soc) = …``). Each cell starts at a known charge (rested, read from
its voltage) but with an unknown polarisation voltage left by an earlier load. Rows every 10 s over
1 h; terminal voltage noise 2 mV, 1 mV resolution; the current is logged on the same rows.

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
I_PARASITIC = 0.25  # A (concealed)
R0, R1, C1 = 0.03, 0.02, 2000.0
DT, DURATION = 10.0, 3600.0
NOISE, RESOLUTION = 0.002, 0.001
EXPERIMENTS = [  # id, role, capacity (A.s), start soc, start polarisation (V), mean current (A), seed
    ("c1", "train", 7200.0, 0.95, 0.02, 1.0, 1), ("c2", "train", 9000.0, 0.90, 0.00, 1.5, 2),
    ("c3", "train", 10800.0, 0.85, 0.035, 1.2, 3), ("c4", "validation", 8100.0, 0.92, 0.01, 1.3, 4),
    ("c5", "test", 12600.0, 0.95, 0.03, 2.0, 5),
]


def ocv(soc: np.ndarray) -> np.ndarray:
    return 3.4 + 0.6 * soc + 0.1 * np.tanh(20 * (soc - 0.1))


def load(t: np.ndarray, mean: float, rng: np.random.Generator) -> np.ndarray:
    """Pulsed discharge: random levels held for 2-10 min, rests in between (A)."""
    out = np.zeros_like(t)
    k = 0
    while k < t.size:
        n = int(rng.integers(12, 60))
        out[k:k + n] = 0.0 if rng.random() < 0.3 else rng.uniform(0.3, 1.7) * mean
        k += n
    return np.round(out, 3)


def record(Q: float, soc0: float, v0: float, mean: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, DURATION + DT / 2, DT)
    current = load(t, mean, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        i = np.interp(tt, t, current)
        return [(-i - I_PARASITIC) / Q, (i - y[1] / R1) / C1]

    sol = solve_ivp(rhs, (0.0, DURATION), [soc0, v0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT)
    assert sol.success, sol.message
    soc, v1 = sol.y
    V = ocv(soc) - R0 * current - v1
    measured = np.round((V + rng.normal(0, NOISE, V.size)) / RESOLUTION) * RESOLUTION
    measured[rng.integers(30, t.size - 30, size=4)] = np.nan
    telemetry = pd.DataFrame({"time": t, "cell.V": measured, "load.i": current})
    truth = pd.DataFrame({"time": t, "cell.soc": soc, "rc.v": v1, "load.i": current, "cell.V": V,
                          "term:cell.soc": np.full(t.size, -I_PARASITIC)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, Q, soc0, v0, mean, seed in EXPERIMENTS:
        telemetry, truth = record(Q, soc0, v0, mean, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} rows, soc {truth['cell.soc'].iloc[0]:.2f} -> {truth['cell.soc'].iloc[-1]:.2f}")


if __name__ == "__main__":
    main()
