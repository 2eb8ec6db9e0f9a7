"""Synthetic telemetry of Li-ion cells under pulsed loads — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC. The real cells follow the engineer's equivalent circuit (``model.py``) plus
one thing he left out: a **constant parasitic discharge** of 0.15 A (self-discharge through a
fault, or a parasitic load on the cell's terminals before the current sensor), a constant sink on
the charge balance,

    cell.Q·der(cell.soc) = −load.i  − 0.15      (A)
                                    ^^^^^^ concealed

on the equation of the state of charge, which is not measured: it shows in the terminal voltage
as a drift of the open-circuit voltage that the logged current does not explain, also during
rests and charge pulses (≈ 0.15·7200/Q of charge over the 2 h record: 60–90 mV on the training
cells, σ = 2 mV). A mis-sized capacity would scale with the current instead; the polarisation
branch (τ = R1·C1 = 200 s) cannot hold a drift.

Each cell starts at a known charge (rested before the test; read from its open-circuit voltage)
but with an **unknown polarisation voltage** ``rc.v`` left by an earlier load (0–45 mV; declared
as a range in the data config).

The logger: rows every 10 s for 2 h with ±1 s jitter; a few rows lost; terminal voltage σ = 2 mV
Gaussian noise and 1 mV resolution, a few readings missing (NaN); the current logged on the same
rows at 1 mA resolution. Load profiles: pulses of random level (0.3–1.7 × the experiment's mean
current) held 1–5 min, rests, and short charge pulses.

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
I_PARASITIC = 0.15  # A (concealed)
R0, R1, C1 = 0.03, 0.02, 10000.0  # Ohm, Ohm, F (as in model.py)
DT, DURATION, JITTER = 10.0, 7200.0, 1.0  # s
NOISE, RESOLUTION = 0.002, 0.001  # V: voltage sensor
CURRENT_RESOLUTION = 0.001  # A
# id, role, capacity cell.Q (A.s), start soc (known), start polarisation rc.v (V, unknown), mean current (A), seed
EXPERIMENTS = [
    ("c1", "train", 7200.0, 0.95, 0.030, 0.75, 21),
    ("c2", "train", 9000.0, 0.90, 0.000, 1.1, 22),
    ("c3", "train", 10800.0, 0.85, 0.045, 1.35, 23),
    ("c4", "validation", 9900.0, 0.92, 0.015, 1.2, 24),
    ("c5", "test", 14400.0, 0.95, 0.040, 1.35, 25),  # a bigger cell than any in training, same currents
]


def ocv(soc: np.ndarray) -> np.ndarray:
    """Open-circuit voltage (V), as in model.py."""
    return 3.4 + 0.6 * soc + 0.1 * np.tanh(20 * (soc - 0.1))


def timestamps(rng: np.random.Generator) -> np.ndarray:
    """Logger rows: nominally every DT, jittered by up to ±JITTER, a few rows lost."""
    t = np.arange(0.0, DURATION + DT / 2, DT)
    t[1:-1] += rng.uniform(-JITTER, JITTER, t.size - 2)
    lost = rng.choice(np.arange(20, t.size - 20), size=5, replace=False)
    return np.round(np.delete(t, lost), 2)


def load(t: np.ndarray, mean: float, rng: np.random.Generator) -> np.ndarray:
    """Current on the logged rows (A, positive out of the cell): pulses held 1–5 min, rests, charge pulses."""
    out = np.empty_like(t)
    k = 0
    while k < t.size:
        u = rng.random()
        if u < 0.25:  # rest
            n, level = int(rng.integers(6, 30)), 0.0
        elif u < 0.35:  # short charge pulse (regeneration)
            n, level = int(rng.integers(3, 12)), -rng.uniform(0.2, 0.8) * mean
        else:  # discharge pulse
            n, level = int(rng.integers(6, 30)), rng.uniform(0.3, 1.7) * mean
        out[k:k + n] = level
        k += n
    return np.round(out / CURRENT_RESOLUTION) * CURRENT_RESOLUTION


def record(Q: float, soc0: float, v0: float, mean: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = timestamps(rng)
    current = load(t, mean, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        i = np.interp(tt, t, current)
        return [(-i - I_PARASITIC) / Q, (i - y[1] / R1) / C1]

    sol = solve_ivp(rhs, (0.0, t[-1]), [soc0, v0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT / 2)
    assert sol.success, sol.message
    soc, v1 = sol.y
    V = ocv(soc) - R0 * current - v1
    measured = np.round((V + rng.normal(0, NOISE, V.size)) / RESOLUTION) * RESOLUTION
    measured[rng.choice(np.arange(20, t.size - 20), size=6, replace=False)] = np.nan
    telemetry = pd.DataFrame({"time": t, "cell.V": measured, "load.i": current})
    truth = pd.DataFrame({"time": t, "cell.soc": soc, "rc.v": v1, "load.i": current, "cell.V": V,
                          "term:cell.soc": np.full(t.size, -I_PARASITIC)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, Q, soc0, v0, mean, seed in EXPERIMENTS:
        telemetry, truth = record(Q, soc0, v0, mean, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        drift = I_PARASITIC * truth["time"].iloc[-1] / Q
        print(f"{exp_id} ({role}): {len(telemetry)} rows, soc {truth['cell.soc'].iloc[0]:.2f} -> {truth['cell.soc'].iloc[-1]:.2f} "
              f"(min {truth['cell.soc'].min():.2f}), current {telemetry['load.i'].min():.2f}..{telemetry['load.i'].max():.2f} A, "
              f"parasitic drift {drift:.3f} of charge")


if __name__ == "__main__":
    main()
