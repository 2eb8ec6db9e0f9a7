"""Synthetic laboratory data of a stirred-tank reactor — deterministic generator holding the truth.

THE DATA ARE SYNTHETIC. The real reactor follows the engineer's model (``model.py``) plus one
thing he left out: a **side reaction** ``A + 2 B → C`` between the reactant and the additive he
took for inert, elementary (second order overall), with rate ``r = k2·A·B``. It takes a term out of
*both* balances — a product of the two measured concentrations, with the stoichiometric factor 2 on
the additive:

    der(reactor.A) = feed.q/reactor.V·(feed.A − reactor.A) − k1·reactor.A   − k2·reactor.A·reactor.B      (mol/(L·min))
    der(reactor.B) = feed.q/reactor.V·(feed.B − reactor.B)                  − 2·k2·reactor.A·reactor.B
                                                                             ^^^^^^^^^^^^^^^^^^^^^^^^^^ concealed

with ``k2 = 0.02 L/(mol·min)``. Time is in minutes (the model's own unit: no seconds anywhere).

The lab: **one** training run and one held-out run, each 4 h; 36 samples drawn by hand at irregular
times (roughly every 7 min, ±3 min) and analysed by HPLC for both concentrations: σ = 0.02 mol/L
on A and 0.03 mol/L on B (about 2–3 % of their level), reported to 0.005 mol/L; one B analysis
lost per run. The feed pump is set by hand between 0.1 and 0.6 L/min a few times per run; its
flow is read off the rotameter at each sample (the model sees it linear between samples, and so
does this generator). The held-out run starts from a different charge (much A, little B) and has
its own feed schedule.

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
K2 = 0.02  # L/(mol.min): side reaction A + 2B -> C (concealed)
V, A_IN, B_IN, K1 = 10.0, 2.0, 3.0, 0.03  # L, mol/L, mol/L, 1/min (as in model.py)
DURATION, SAMPLES = 240.0, 36  # min, samples per run
NOISE = {"reactor.A": 0.02, "reactor.B": 0.03}  # mol/L
RESOLUTION = 0.005  # mol/L
FLOW_RESOLUTION = 0.01  # L/min
# id, role, initial charge (A, B) in mol/L, seed
EXPERIMENTS = [
    ("r1", "train", (0.2, 2.5), 31),
    ("r2", "test", (1.6, 0.4), 32),  # much reactant, little additive: a charge not seen in training
]


def side_reaction(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The concealed terms of ``der(reactor.A) = …`` and ``der(reactor.B) = …`` (mol/(L·min))."""
    r = K2 * a * b
    return -r, -2.0 * r


def sample_times(rng: np.random.Generator) -> np.ndarray:
    """Hand-drawn samples: nominally evenly spread over the run, each up to ±3 min off (min)."""
    t = np.linspace(0.0, DURATION, SAMPLES)
    t[1:-1] += rng.uniform(-3.0, 3.0, SAMPLES - 2)
    return np.round(np.sort(t), 1)


def feed(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Feed flow read at the samples (L/min): a few hand-set levels, moved between samples."""
    knots = np.sort(rng.uniform(15.0, DURATION - 15.0, 5))
    levels = rng.uniform(0.1, 0.6, knots.size + 1)
    steps = levels[np.searchsorted(knots, t)]
    return np.round(steps / FLOW_RESOLUTION) * FLOW_RESOLUTION


def record(start: tuple[float, float], seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    t = sample_times(rng)
    q = feed(t, rng)

    def rhs(tt: float, s: np.ndarray) -> list[float]:
        a, b = s
        qq = np.interp(tt, t, q)  # the input as the model sees it: linear between recorded rows
        da, db = side_reaction(a, b)
        return [qq / V * (A_IN - a) - K1 * a + da, qq / V * (B_IN - b) + db]

    sol = solve_ivp(rhs, (0.0, DURATION), list(start), t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=0.5)
    assert sol.success, sol.message
    a, b = sol.y
    measured = {name: np.round((v + rng.normal(0, NOISE[name], v.size)) / RESOLUTION) * RESOLUTION
                for name, v in (("reactor.A", a), ("reactor.B", b))}
    measured["reactor.B"][rng.integers(5, SAMPLES - 5)] = np.nan  # one B analysis lost
    da, db = side_reaction(a, b)
    telemetry = pd.DataFrame({"time": t, **measured, "feed.q": q})
    truth = pd.DataFrame({"time": t, "reactor.A": a, "reactor.B": b, "feed.q": q,
                          "term:reactor.A": da, "term:reactor.B": db})
    return telemetry, truth


def model_as_written(start: tuple[float, float], truth: pd.DataFrame) -> np.ndarray:
    """The engineer's model (no side reaction) on the same feed, for the printed summary."""
    t, q = truth["time"].to_numpy(), truth["feed.q"].to_numpy()

    def rhs(tt: float, s: np.ndarray) -> list[float]:
        qq = np.interp(tt, t, q)
        return [qq / V * (A_IN - s[0]) - K1 * s[0], qq / V * (B_IN - s[1])]

    return solve_ivp(rhs, (0.0, DURATION), list(start), t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12, max_step=0.5).y


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, start, seed in EXPERIMENTS:
        telemetry, truth = record(start, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        sim = model_as_written(start, truth)
        parts = []
        for j, name in enumerate(("reactor.A", "reactor.B")):
            meas = telemetry[name].to_numpy()
            ok = np.isfinite(meas)
            rmse = float(np.sqrt(np.mean((sim[j][ok] - meas[ok]) ** 2)))
            parts.append(f"{name} {truth[name].min():.2f}..{truth[name].max():.2f} mol/L, term up to "
                         f"{-truth['term:' + name].min():.3f} mol/(L·min), model as written RMSE {rmse:.3f} ({rmse / NOISE[name]:.0f} σ)")
        print(f"{exp_id} ({role}): {len(telemetry)} samples, feed {telemetry['feed.q'].min():.2f}..{telemetry['feed.q'].max():.2f} L/min; "
              + "; ".join(parts))


if __name__ == "__main__":
    main()
