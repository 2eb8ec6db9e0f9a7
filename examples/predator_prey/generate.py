"""Synthetic census data of prey and predators — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC: the real populations follow the engineer's model (``model.py``) plus the
**predation loss of the prey**, ``-a·prey.x·pred.y`` with ``a = 0.5`` (a product of two states),
which the engineer's prey equation leaves out. Time is dimensionless (``tu``, no seconds). Each
census has 40 counts at irregular times over 30 tu; both counts carry Gaussian noise (σ 0.10
kanimals on prey, 0.04 on predators, about 3–4 % of their typical level) and are rounded to 10
animals; one predator count per census is missing. Prey are stocked from a hatchery at a recorded
rate ``stocking.u`` (kanimals/tu) that changes every few tu, which keeps the populations swinging.

    python generate.py        # writes telemetry/ and truth/ beside this file
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
A = 0.5  # predation loss coefficient (concealed), 1/(kanimals.tu)
R, B, D, E = 1.0, 0.2, 0.6, 0.15  # as the engineer has them (model.py)
DURATION, ROWS = 30.0, 40  # tu, counts per census
NOISE = {"prey.x": 0.10, "pred.y": 0.04}  # kanimals
RESOLUTION = 0.01  # kanimals: counts are reported to 10 animals
EXPERIMENTS = [  # id, role, carrying capacity K, prey start, predator start, seed
    ("h1", "train", 5.0, 2.0, 1.0, 1), ("h2", "train", 7.0, 1.0, 0.5, 2), ("h3", "train", 9.0, 4.0, 2.5, 3),
    ("h4", "validation", 6.0, 1.5, 1.5, 4), ("h5", "test", 8.0, 0.6, 2.8, 5),
]


def predation(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The concealed term of ``der(prey.x) = …`` (kanimals/tu)."""
    return -A * x * y


def stocking(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Hatchery stocking rate at the census times (kanimals/tu): random piecewise-linear, some pauses."""
    knots = np.arange(0.0, DURATION + 3.0, 3.0)
    levels = np.where(rng.random(knots.size) < 0.25, 0.0, rng.uniform(0.2, 2.0, knots.size))
    return np.round(np.interp(t, knots, levels), 2)


def record(K: float, x0: float, y0: float, seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = np.round(np.sort(np.concatenate([[0.0, DURATION], rng.uniform(0.3, DURATION - 0.3, ROWS - 2)])), 3)
    u = stocking(t, rng)

    def rhs(tt: float, s: np.ndarray) -> list[float]:
        x, y = s
        uu = np.interp(tt, t, u)  # the input as the model sees it: linear between recorded rows
        return [R * x * (1 - x / K) + uu + predation(x, y), B * x * y - D * y - E * y**2]

    sol = solve_ivp(rhs, (0.0, DURATION), [x0, y0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=0.05)
    assert sol.success, sol.message
    x, y = sol.y
    counted = {name: np.round((v + rng.normal(0, NOISE[name], v.size)) / RESOLUTION) * RESOLUTION
               for name, v in (("prey.x", x), ("pred.y", y))}
    counted["pred.y"][rng.integers(5, ROWS - 5)] = np.nan  # one predator count missing
    telemetry = pd.DataFrame({"time": t, **counted, "stocking.u": u})
    truth = pd.DataFrame({"time": t, "prey.x": x, "pred.y": y, "stocking.u": u, "term:prey.x": predation(x, y)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, _, K, x0, y0, seed in EXPERIMENTS:
        telemetry, truth = record(K, x0, y0, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        print(f"experiment {exp_id}: {len(telemetry)} counts, prey {truth['prey.x'].min():.2f}–"
              f"{truth['prey.x'].max():.2f}, predators {truth['pred.y'].min():.2f}–{truth['pred.y'].max():.2f}")


if __name__ == "__main__":
    main()
