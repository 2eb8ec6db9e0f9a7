"""Synthetic telemetry of belt conveyors — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC. The real conveyors follow the engineer's model (``model.py``) plus one
thing he left out: the **rolling resistance of the idler rollers** that carry the belt, one set
every metre, each turning against its own bearing and seal drag — a force proportional to the belt
speed *and to the number of idlers, i.e. to the belt's length*,

    (drive.m + belt.mu·belt.L)·der(belt.v) = drive.k·motor.i − drive.b·belt.v  − c·belt.L·belt.v   (N)
                                                                               ^^^^^^^^^^^^^^^^^ concealed

with ``c = 2.5 N·s/m²`` (per metre of conveyor, per m/s). Only two installations are recorded for
training (20 m and 40 m of belt); the held-out one is 80 m long, outside the training range, so a
correction that does not scale with ``belt.L`` carries the wrong coefficient there.

The logger: rows every 0.5 s for 5 min with ±0.1 s jitter, a few rows lost; the belt speed from a
tachometer wheel, σ = 0.01 m/s Gaussian noise, 0.005 m/s resolution, a 2 s dropout per record; the
motor current (the model's input) on the same rows at 0.01 A resolution. Drive profiles: current
levels between 2 and 10 A held 8–25 s, reached by a step or a soft-start ramp, and one stop
(0 A, the belt coasts down) per record; every record starts from standstill.

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
C_IDLER = 2.5  # N.s/m2: idler resistance per metre of conveyor per m/s (concealed)
M0, MU, K, B = 400.0, 8.0, 60.0, 300.0  # kg, kg/m, N/A, N.s/m (as in model.py)
DT, DURATION, JITTER = 0.5, 300.0, 0.1  # s
NOISE, RESOLUTION = 0.01, 0.005  # m/s: tachometer
CURRENT_RESOLUTION = 0.01  # A
# id, role, belt length belt.L (m), seed
EXPERIMENTS = [
    ("k1", "train", 20.0, 21),
    ("k2", "train", 40.0, 22),
    ("k3", "test", 80.0, 23),  # a length not seen in training (and outside its range)
]


def idlers(length: float, v: np.ndarray) -> np.ndarray:
    """The concealed term of ``(drive.m + belt.mu·belt.L)·der(belt.v) = …`` (N)."""
    return -C_IDLER * length * v + 0.0  # + 0.0: no negative zero at standstill


def timestamps(rng: np.random.Generator) -> np.ndarray:
    """Logger rows: nominally every DT, jittered by up to ±JITTER, a few rows lost."""
    t = np.arange(0.0, DURATION + DT / 2, DT)
    t[1:-1] += rng.uniform(-JITTER, JITTER, t.size - 2)
    lost = rng.choice(np.arange(20, t.size - 20), size=6, replace=False)
    return np.round(np.delete(t, lost), 3)


def current(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Motor current on the logged rows (A): levels held 8–25 s, step or ramp, one stop."""
    out = np.empty_like(t)
    level, k, stopped = 0.0, 0, False
    while k < t.size:
        n = int(rng.integers(16, 50))  # rows (~0.5 s each)
        stop = not stopped and k > t.size // 3 and rng.random() < 0.5
        new = 0.0 if stop else rng.uniform(2.0, 10.0)
        stopped = stopped or stop
        ramp = int(rng.integers(4, 12)) if rng.random() < 0.4 else 1
        seg = np.full(n, new)
        seg[:min(ramp, n)] = level + (new - level) * np.arange(1, min(ramp, n) + 1) / ramp
        out[k:k + n] = seg[:t.size - k]
        level, k = new, k + n
    return np.round(out / CURRENT_RESOLUTION) * CURRENT_RESOLUTION


def record(length: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = timestamps(rng)
    i = current(t, rng)
    mass = M0 + MU * length

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        ii = np.interp(tt, t, i)  # the input as the model sees it: linear between logged rows
        return [(K * ii - B * y[0] + idlers(length, y[0])) / mass]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT / 2)
    assert sol.success, sol.message
    v = sol.y[0]
    measured = np.round((v + rng.normal(0, NOISE, v.size)) / RESOLUTION) * RESOLUTION
    gap = int(rng.integers(50, t.size - 50))
    measured[gap:gap + 4] = np.nan  # the tachometer wheel lifted off the belt for ~2 s
    telemetry = pd.DataFrame({"time": t, "belt.v": measured, "motor.i": i})
    truth = pd.DataFrame({"time": t, "belt.v": v, "motor.i": i, "term:belt.v": idlers(length, v)})
    return telemetry, truth


def model_as_written(length: float, truth: pd.DataFrame) -> np.ndarray:
    """The engineer's model (no idler resistance) on the same input, for the printed summary."""
    t, i = truth["time"].to_numpy(), truth["motor.i"].to_numpy()
    mass = M0 + MU * length
    sol = solve_ivp(lambda tt, y: [(K * np.interp(tt, t, i) - B * y[0]) / mass], (0.0, t[-1]), [0.0],
                    t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=DT / 2)
    return sol.y[0]


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, length, seed in EXPERIMENTS:
        telemetry, truth = record(length, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        measured = telemetry["belt.v"].to_numpy()
        ok = np.isfinite(measured)
        rmse = float(np.sqrt(np.mean((model_as_written(length, truth)[ok] - measured[ok]) ** 2)))
        print(f"{exp_id} ({role}, L = {length:g} m): {len(telemetry)} rows, belt.v {truth['belt.v'].min():.2f}.."
              f"{truth['belt.v'].max():.2f} m/s, idler force up to {-truth['term:belt.v'].min():.0f} N, "
              f"model as written RMSE {rmse:.3f} m/s ({rmse / NOISE:.0f} σ)")


if __name__ == "__main__":
    main()
