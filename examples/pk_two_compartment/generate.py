"""Synthetic plasma concentrations of patients on intravenous infusions — deterministic generator
holding the truth.

THE DATA ARE SYNTHETIC. The real patients follow the engineer's two-compartment model
(``model.py``) plus one thing he left out: a **saturable (Michaelis–Menten) elimination** from the
central compartment, an enzyme pathway that saturates at high concentration,

    der(central.A) = infusion.rate − CL·C − Q·(C − C_p)  − Vmax·C/(Km + C)      (mg/h)
                                                        ^^^^^^^^^^^^^^^^^^ concealed

with C = central.A/central.V, Vmax = 40 mg/h and Km = 2 mg/L, on the equation of the central
amount. The declared linear clearance (CL = 2 L/h), the distribution (Q = 8 L/h) and the
peripheral volume (25 L) are the true ones. At low concentrations the hidden path looks like an
extra linear clearance of Vmax/Km = 20 L/h (ten times the declared one); at 10–15 mg/L it carries
only a sixth to an eighth of that. Why it is identifiable: the training patients are dosed from
troughs well below Km to peaks 5–7.5× Km, so no constant clearance fits both: the best extra
*linear* clearance (6.1 L/h, fitted by output-error least squares on s1–s3) still misses by
0.55 mg/L RMSE (≈ 11 σ) there and by 1.8 mg/L on the high-dose test patient s6, while the
saturable term fits to the noise. The model as written misses by 4.1–6.5 mg/L (80–130 σ) on
s1–s3, 5.6 mg/L on s5 and 8.4 mg/L on s6: it lets the drug accumulate.

The study: every patient starts drug-free; a pre-dose sample at 0 h, then plasma samples every
30 min for 48 h (97 samples) with ±2 min timing jitter; the assay has σ = 0.05 mg/L additive
Gaussian noise and reports to 0.01 mg/L; a few samples are missing (NaN). The infusion pump's
log is merged into the same file: at each start and stop it adds two rows 0.01 h (36 s) apart
holding the rate before and after the change (concentration empty), so the linear interpolation
of the ``infusion.rate`` column is the piecewise-constant programme (all switches fall on a
quarter past or to the hour, away from the samples). Programmes: 4–5 infusions of 0.5–4 h at
50–400 mg/h with pauses; the central volume differs per patient (data config).

    python generate.py        # writes telemetry/ and truth/ beside this file (byte-identical on rerun)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

HERE = Path(__file__).resolve().parent
VMAX, KM = 40.0, 2.0  # mg/h, mg/L (concealed)
CL, Q, VP = 2.0, 8.0, 25.0  # L/h, L/h, L: clearance.CL, distribution.Q, peripheral.V (as in model.py)
DT, DURATION, JITTER = 0.5, 48.0, 2.0 / 60.0  # h: a sample every 30 min for 48 h, ±2 min
TIME_RESOLUTION = 0.001  # h (3.6 s)
PUMP_STEP = 0.01  # h: the pump log's two rows at each start and stop (before, after)
NOISE, RESOLUTION = 0.05, 0.01  # mg/L: assay
# id, role, central volume central.V (L), infusion programme [(start h, duration h, rate mg/h)], seed
EXPERIMENTS = [
    ("s1", "train", 8.0, [(0.25, 1.0, 100), (8.25, 2.0, 80), (20.25, 0.5, 200), (30.25, 4.0, 50), (40.75, 1.0, 150)], 31),
    ("s2", "train", 12.0, [(0.25, 2.0, 150), (12.25, 1.0, 250), (24.75, 3.0, 100), (36.25, 0.5, 300)], 32),
    ("s3", "train", 10.0, [(0.25, 0.5, 300), (6.25, 3.0, 120), (18.75, 1.5, 200), (30.25, 2.0, 60), (40.25, 1.0, 250)], 33),
    ("s4", "validation", 15.0, [(0.25, 1.5, 250), (10.25, 2.5, 120), (26.25, 1.0, 300), (36.75, 2.0, 80)], 34),
    ("s5", "test", 11.0, [(0.25, 1.0, 200), (8.75, 2.0, 100), (20.25, 3.0, 120), (34.25, 0.5, 300)], 35),
    ("s6", "test", 9.0, [(0.25, 1.0, 350), (10.25, 1.5, 300), (24.25, 3.0, 200), (38.25, 0.5, 400)], 36),  # higher doses
]


def saturable(A: np.ndarray, V: float) -> np.ndarray:
    """The concealed term of ``der(central.A) = …`` (mg/h): Michaelis–Menten elimination."""
    C = A / V
    return -VMAX * C / (KM + C) + 0.0  # + 0.0: no "-0" in the files


def sample_times(rng: np.random.Generator) -> np.ndarray:
    """Plasma samples: nominally every DT, jittered by up to ±JITTER (the pre-dose and last ones on time)."""
    t = np.arange(0.0, DURATION + DT / 2, DT)
    t[1:-1] += rng.uniform(-JITTER, JITTER, t.size - 2)
    return np.round(t / TIME_RESOLUTION) * TIME_RESOLUTION


def pump_log(programme: list[tuple[float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """The pump's rows (h, mg/h): at each start and stop the rate before and, PUMP_STEP later, after."""
    times, rates = [], []
    for start, duration, rate in programme:
        for at, before, after in ((start, 0.0, rate), (start + duration, rate, 0.0)):
            times += [at, at + PUMP_STEP]
            rates += [before, after]
    times = np.round(np.array(times) / TIME_RESOLUTION) * TIME_RESOLUTION
    assert np.all(np.diff(times) > 0), "infusions overlap"
    return times, np.array(rates, dtype=float)


def record(V: float, programme: list[tuple[float, float, float]], seed: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    ts = sample_times(rng)
    tp, rp = pump_log(programme)
    t = np.concatenate([ts, tp])
    order = np.argsort(t, kind="stable")
    t = t[order]
    assert np.all(np.diff(t) > 0), "a sample falls on a pump row"
    is_sample = np.concatenate([np.ones(ts.size, bool), np.zeros(tp.size, bool)])[order]
    # the programme on every row: the pump's own rows as logged, the samples between them (never inside a change)
    rate = np.interp(t, np.concatenate([[0.0], tp, [DURATION]]), np.concatenate([[0.0], rp, [0.0]]))
    for start, duration, r in programme:
        inside = is_sample & (t > start) & (t < start + duration + PUMP_STEP)
        assert np.all((t[inside] >= start + PUMP_STEP) & (t[inside] <= start + duration)), "a sample inside a change"

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        Ac, Ap = y
        C, Cp = Ac / V, Ap / VP
        u = np.interp(tt, t, rate)  # the input as the model sees it: linear between recorded rows
        return [u - CL * C - Q * (C - Cp) + saturable(Ac, V), Q * (C - Cp)]

    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-10, atol=1e-12,
                    max_step=PUMP_STEP / 2)
    assert sol.success, sol.message
    Ac, Ap = sol.y
    C = Ac / V
    measured = np.round((C + rng.normal(0, NOISE, C.size)) / RESOLUTION) * RESOLUTION
    measured[~is_sample] = np.nan  # pump rows: no sample
    samples = np.flatnonzero(is_sample)
    measured[rng.choice(samples[4:-4], size=3, replace=False)] = np.nan  # missing samples
    telemetry = pd.DataFrame({"time": t, "central.C": measured, "infusion.rate": rate})
    truth = pd.DataFrame({"time": t, "central.A": Ac, "peripheral.A": Ap, "infusion.rate": rate, "central.C": C,
                          "peripheral.C": Ap / VP, "term:central.A": saturable(Ac, V)})
    return telemetry, truth


def main() -> None:
    for folder in ("telemetry", "truth"):
        (HERE / folder).mkdir(exist_ok=True)
    for exp_id, role, V, programme, seed in EXPERIMENTS:
        telemetry, truth = record(V, programme, seed)
        telemetry.to_csv(HERE / "telemetry" / f"{exp_id}.csv", index=False, float_format="%.6g")
        truth.to_csv(HERE / "truth" / f"{exp_id}.csv", index=False, float_format="%.8g")
        C = truth["central.C"].to_numpy()
        dose = sum(d * r for _, d, r in programme)
        print(f"{exp_id} ({role}): {len(telemetry)} rows ({telemetry['central.C'].notna().sum()} samples), "
              f"central.V {V:g} L, {len(programme)} infusions, {dose:g} mg in all, "
              f"C {C[C > 0].min():.2f}..{C.max():.2f} mg/L, saturable path up to {-truth['term:central.A'].min():.1f} mg/h")


if __name__ == "__main__":
    main()
