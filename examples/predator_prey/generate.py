"""Synthetic census data of prey and predators — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real populations follow the engineer's model (``model.py``) plus the
**predation loss of the prey**, ``-a·prey.x·pred.y`` with ``a = 0.5`` (a product of two states),
which the engineer's prey equation leaves out. Time is dimensionless (``tu``); each census has 40
counts at irregular times over 30 tu, with 4 % multiplicative noise, rounded to 10 animals.

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
A = 0.5  # predation loss coefficient (concealed), 1/(kanimals.tu)
R, B, D, E = 1.0, 0.3, 0.6, 0.2
DURATION, ROWS, NOISE = 30.0, 40, 0.04
EXPERIMENTS = [  # id, role, K, x0, y0, seed
    ("h1", "train", 4.0, 2.0, 1.0, 1), ("h2", "train", 5.0, 1.0, 0.6, 2), ("h3", "train", 6.0, 3.0, 1.5, 3),
    ("h4", "validation", 5.5, 1.5, 1.2, 4), ("h5", "test", 7.0, 4.0, 0.5, 5),
]


def predation(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The concealed term of ``der(prey.x) = …`` (kanimals/tu)."""
    return -A * x * y


def record(K: float, x0: float, y0: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.sort(np.concatenate([[0.0], rng.uniform(0.2, DURATION, ROWS - 1)]))
    t = np.round(t, 3)

    def rhs(_: float, s: np.ndarray) -> list[float]:
        x, y = s
        return [R * x * (1 - x / K) + predation(x, y), B * x * y - D * y - E * y**2]

    sol = solve_ivp(rhs, (0.0, DURATION), [x0, y0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12)
    assert sol.success, sol.message
    x, y = sol.y
    noisy = lambda v: np.round(v * (1 + rng.normal(0, NOISE, v.size)), 2)  # noqa: E731
    telemetry = pd.DataFrame({"time": t, "prey.x": noisy(x), "pred.y": noisy(y)})
    telemetry.loc[rng.integers(5, ROWS - 5), "pred.y"] = np.nan  # one predator count missing
    truth = pd.DataFrame({"time": t, "prey.x": x, "pred.y": y, "term:prey.x": predation(x, y)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, K, x0, y0, seed in EXPERIMENTS:
        telemetry, truth = record(K, x0, y0, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} counts")


if __name__ == "__main__":
    main()
