"""Synthetic telemetry of a self-excited DC shunt generator — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real machine follows the engineer's model (``model.py``) except that
its iron **saturates**. The engineer took the magnetisation line as straight, emf
``E = w·(k_r + G·i)``; the real one bends over as Froelich's curve, ``E = w·(k_r + G·i/(1 + i/b))``
with b = 3 A (the same slope G = 0.5 V·s/(rad·A) at small currents). On the field equation

    field.L·der(field.i) = armature.E − field.R·field.i  − 0.5·shaft.w·field.i²/(3 + field.i)     (V)
                                                          ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^ concealed

Without it the model is a positive-feedback loop with nothing to stop it: once G·w exceeds the
field resistance the field current grows exponentially (rate (G·w − R)/L, about 0.3–1.2 /s here),
past 1e6 A within 20 s of a 30 s record; the real machine settles at 0.5–3 A, where the bent
curve meets the field resistance line, and follows the speed.

The logger: rows every 50 ms for 30 s from the closing of the field switch (field current 0);
the field current read on a shunt with σ = 5 mA noise and 1 mA resolution, a few readings
missing; the shaft speed from a tachometer (0.1 rad/s resolution) on the same rows. The prime
mover holds random speeds 3–8 s, reached by a step or a ramp; the field rheostat is set per run.

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
B_SAT = 3.0  # A: field current at which the emf slope has halved (concealed)
L, K_R, G = 20.0, 0.01, 0.5  # H, V.s/rad, V.s/(rad.A): as in model.py
DT, DURATION = 0.05, 30.0  # s
NOISE, RESOLUTION = 0.005, 0.001  # A: field current shunt
SPEED_RESOLUTION = 0.1  # rad/s
# id, role, field.R (Ohm), speed range (rad/s), seed
EXPERIMENTS = [
    ("s1", "train", 50.0, (130.0, 170.0), 31),
    ("s2", "train", 54.0, (135.0, 175.0), 32),
    ("s3", "train", 58.0, (140.0, 180.0), 33),
    ("s4", "validation", 52.0, (135.0, 170.0), 34),
    ("s5", "test", 46.0, (150.0, 185.0), 35),  # a rheostat setting and speeds not seen in training
]


def saturation(i: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The concealed term of ``field.L·der(field.i) = …`` (V)."""
    i, w = np.asarray(i), np.asarray(w)
    return -G * w * i**2 / (B_SAT + i) + 0.0  # + 0.0: no "-0" in the files


def speed(t: np.ndarray, low: float, high: float, rng: np.random.Generator) -> np.ndarray:
    """Shaft speed on the logged rows (rad/s): levels held 3-8 s, reached by a step or a 1-3 s ramp."""
    out = np.empty_like(t)
    level, k = rng.uniform(low, high), 0
    while k < t.size:
        n = int(rng.integers(60, 160))
        new = rng.uniform(low, high)
        ramp = int(rng.integers(20, 60)) if rng.random() < 0.6 else 1
        seg = np.full(n, new)
        m = min(ramp, n)
        seg[:m] = level + (new - level) * np.arange(1, m + 1) / ramp
        out[k:k + n] = seg[:t.size - k]
        level, k = new, k + n
    return np.round(out / SPEED_RESOLUTION) * SPEED_RESOLUTION


def record(R: float, speeds: tuple[float, float], seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(0.0, DURATION + DT / 2, DT), 6)
    w = speed(t, *speeds, rng)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        ww = np.interp(tt, t, w)
        return [(ww * (K_R + G * y[0]) - R * y[0] + saturation(y[0], ww)) / L]

    sol = solve_ivp(rhs, (0.0, DURATION), [0.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT)
    assert sol.success, sol.message
    i = sol.y[0]
    measured = np.round((i + rng.normal(0.0, NOISE, t.size)) / RESOLUTION) * RESOLUTION
    measured[rng.choice(np.arange(20, t.size - 20), size=5, replace=False)] = np.nan
    telemetry = pd.DataFrame({"time": t, "field.i": measured, "shaft.w": w})
    truth = pd.DataFrame({"time": t, "field.i": i, "shaft.w": w, "term:field.i": saturation(i, w)})
    return telemetry, truth


def as_written(R: float, t: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The model as written on the same speed record (for the printout only): it runs away."""
    sol = solve_ivp(lambda tt, y: [(np.interp(tt, t, w) * (K_R + G * y[0]) - R * y[0]) / L], (0.0, t[-1]), [0.0],
                    t_eval=t, method="LSODA", rtol=1e-8, atol=1e-12)
    return sol.y[0]


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, R, speeds, seed in EXPERIMENTS:
        telemetry, truth = record(R, speeds, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        t, w, i = truth["time"].to_numpy(), truth["shaft.w"].to_numpy(), truth["field.i"].to_numpy()
        model = as_written(R, t, w)
        past = t[np.argmax(model > 1e6)] if (model > 1e6).any() else float("nan")
        print(f"{exp_id} ({role}): {len(telemetry)} rows, field.R {R:.0f} Ohm, speed {w.min():.0f}..{w.max():.0f} rad/s, "
              f"field.i {i.min():.2f}..{i.max():.2f} A (after 5 s: {i[t >= 5].min():.2f}..), "
              f"saturation term down to {truth['term:field.i'].min():.1f} V; as written: {model[-1]:.2g} A at the end, "
              f"past 1e6 A at {past:.1f} s")


if __name__ == "__main__":
    main()
