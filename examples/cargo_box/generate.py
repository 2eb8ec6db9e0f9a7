"""Synthetic telemetry of the two-zone cargo box — deterministic generator.

THE DATA ARE SYNTHETIC. They are recorded from a simulated "real" box (:mod:`.truth`): the
engineer's model plus one concealed effect, buoyancy-driven air leakage through gaps in the
bulkhead, ``Q = c·ΔT·sqrt(|ΔT|)`` from zone 1 air to zone 2 air. The engineer's model does not
contain it; finding it is the job of physmend. The noise-free truth goes to ``truth/`` for the
proving suite's scorer.

Three experiments, after the seed paper's table (12 hours each, the box soaked at ambient at
the start, a pull-down, then regulation):

==  ============  ============  ==============  ==============
ID  zone1.length  zone2.length  zone 1 setpoint zone 2 setpoint
==  ============  ============  ==============  ==============
1   9.0 m         4.5 m         -20 °C          0 °C
2   2.5 m         11.0 m        -25 °C          4 °C
3   4.5 m         9.0 m         -20 °C          2 °C
==  ============  ============  ==============  ==============

How a record is made (per experiment, fixed seed):

* Logger rows every ~60 s with ±3 s timestamp jitter (irregular); a few rows are missing.
* Ambient ``ambient.T``: a diurnal sine (own phase and amplitude per experiment) plus slow random
  wander, logged every 5th row (~300 s; empty in the rows between), quantised to 0.1 K.
* Cooling ``zoneN.cooling.Q`` (W, >= 0): a discrete PI controller per zone with saturation
  ``0..Q_max`` and anti-windup acts on the measured zone temperature at each logged row k and
  decides the next cooling sample ``Q_{k+1}``; logged every row, rounded to 1 W. The controller
  exists only here: the engineer's model receives the recorded cooling as an input.
* The truth is integrated row interval by row interval (scipy Radau, rtol = atol = 1e-8) with
  inputs that are **exactly** the piecewise-linear interpolation of the logged input samples
  (cooling ramps from ``Q_k`` to ``Q_{k+1}``; ambient between its logged samples) — the same
  signals a model sees when it interpolates the recorded inputs.
* Zone temperatures ``zoneN.air.T``: truth + Gaussian noise (σ = 0.1 K), quantised to 0.1 K;
  three dropout windows of 10–30 min have no zone temperature.

Regenerate the shipped files (byte-identical on every run)::

    python generate.py            # into telemetry/ beside it
    python generate.py --out DIR
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from _numeric import NumpyModel, piecewise_linear_inputs
from model import INPUTS, OUTPUTS
from truth import build_truth_model, true_leakage

TELEMETRY_DIR = Path(__file__).resolve().parent / "telemetry"
TRUTH_DIR = Path(__file__).resolve().parent / "truth"
COLUMNS = ("time", *OUTPUTS, *INPUTS)

BASE_SEED = 20240611
DURATION = 12 * 3600.0  # s
ROW_PERIOD = 60.0  # s, nominal logger period
JITTER = 3.0  # s, max timestamp jitter (uniform)
AMBIENT_EVERY = 5  # ambient is logged on every 5th row (~300 s)
NOISE_SIGMA = 0.1  # K, zone temperature sensor noise
RESOLUTION = 0.1  # K, quantisation of logged temperatures
N_MISSING_ROWS = 4
DROPOUTS_MIN = ((10, 30), (10, 30), (10, 30))  # three dropout windows, minutes (min, max)


@dataclass(frozen=True)
class PISettings:
    """Discrete PI controller of one zone: gain W/K, integral time s, cooling limit W."""

    kp: float
    ti: float
    q_max: float


ZONE_CONTROL = {
    "zone1": PISettings(kp=400.0, ti=1200.0, q_max=5000.0),
    "zone2": PISettings(kp=400.0, ti=1200.0, q_max=3000.0),
}


@dataclass(frozen=True)
class Experiment:
    """One recorded experiment: configuration, setpoints (degC), start conditions, ambient shape."""

    id: str
    zone1_length: float  # m
    zone2_length: float  # m
    setpoint1: float  # degC
    setpoint2: float  # degC
    T_initial: float  # degC, box soaked at the starting ambient temperature
    start_hour: float  # local hour of day at t = 0 (phase of the diurnal ambient)
    diurnal_amplitude: float  # K
    role: str  # train | validation | test

    @property
    def file(self) -> str:
        return f"exp{self.id}.csv"

    @property
    def parameters(self) -> dict[str, float]:
        """Model parameters that differ per experiment (as in the data config)."""
        return {"zone1.length": self.zone1_length, "zone2.length": self.zone2_length, "box.T_initial": self.T_initial}

    @property
    def setpoints(self) -> dict[str, float]:
        return {"zone1": self.setpoint1, "zone2": self.setpoint2}


EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment("1", 9.0, 4.5, -20.0, 0.0, T_initial=28.0, start_hour=8.0, diurnal_amplitude=5.0, role="train"),
    Experiment("2", 2.5, 11.0, -25.0, 4.0, T_initial=26.0, start_hour=14.0, diurnal_amplitude=4.0, role="test"),
    Experiment("3", 4.5, 9.0, -20.0, 2.0, T_initial=30.0, start_hour=19.0, diurnal_amplitude=6.0, role="train"),
)


# -- exogenous signals and logger grid ---------------------------------------------------------
def ambient_signal(exp: Experiment, rng: np.random.Generator) -> Callable[[np.ndarray], np.ndarray]:
    """True ambient temperature (degC) as a function of time (s); equals ``exp.T_initial`` at t = 0.

    Diurnal sine peaking at 15:00 local time plus slow wander (three random sinusoids with
    periods of 1.5–5 h, amplitudes ~0.6 K).
    """
    periods = rng.uniform(1.5, 5.0, size=3) * 3600.0
    amps = rng.normal(0.0, 0.6, size=3)
    phases = rng.uniform(0.0, 2 * np.pi, size=3)

    def raw(t: np.ndarray) -> np.ndarray:
        hour = exp.start_hour + np.asarray(t, dtype=float) / 3600.0
        diurnal = exp.diurnal_amplitude * np.sin(2 * np.pi * (hour - 9.0) / 24.0)
        wander = sum(a * np.sin(2 * np.pi * np.asarray(t) / P + f) for a, P, f in zip(amps, periods, phases))
        return diurnal + wander

    offset = exp.T_initial - float(raw(np.array(0.0)))
    return lambda t: raw(t) + offset


def logger_rows(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Row timestamps (s, 0.1 s resolution, strictly increasing) and their nominal indices.

    Nominal row k is at ``k·60 s`` ± jitter; the first (0 s) and last (12 h) rows are exact.
    ``N_MISSING_ROWS`` interior rows that are not ambient rows are dropped.
    """
    n = int(round(DURATION / ROW_PERIOD))
    k = np.arange(n + 1)
    t = k * ROW_PERIOD + rng.uniform(-JITTER, JITTER, size=n + 1)
    t[0], t[-1] = 0.0, DURATION
    t = np.round(t, 1)
    candidates = k[(k > 1) & (k < n - 1) & (k % AMBIENT_EVERY != 0)]
    dropped = rng.choice(candidates, size=N_MISSING_ROWS, replace=False)
    keep = ~np.isin(k, dropped)
    return t[keep], k[keep]


def dropout_mask(times: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Boolean ``(n_rows,)``: True where zone temperatures are missing (sensor dropouts).

    One window per entry of ``DROPOUTS_MIN``, each in its own third of the record (after the
    first 30 min), lasting a random 10–30 min.
    """
    mask = np.zeros(times.shape, dtype=bool)
    thirds = np.linspace(1800.0, DURATION - 1800.0, len(DROPOUTS_MIN) + 1)
    for (lo, hi), a, b in zip(DROPOUTS_MIN, thirds[:-1], thirds[1:]):
        length = rng.uniform(lo, hi) * 60.0
        start = rng.uniform(a, b - length)
        mask |= (times >= start) & (times < start + length)
    return mask


def quantise(values: np.ndarray, step: float = RESOLUTION) -> np.ndarray:
    """Round to multiples of ``step`` (−0.0 becomes 0.0)."""
    return np.round(np.asarray(values) / step) * step + 0.0


# -- controller and closed-loop truth simulation -------------------------------------------------
class PIController:
    """Discrete PI with saturation ``0..q_max`` and conditional integration (anti-windup).

    ``update(y, dt)`` takes the measured temperature (degC) and the time since the previous
    update (s) and returns the cooling command (W) to reach at the next sample.
    """

    def __init__(self, settings: PISettings, setpoint: float) -> None:
        self.s = settings
        self.setpoint = setpoint
        self.integral = 0.0

    def update(self, y: float, dt: float) -> float:
        e = y - self.setpoint  # positive error: too warm, cool more
        trial = self.integral + self.s.kp * e * dt / self.s.ti
        q = self.s.kp * e + trial
        if 0.0 <= q <= self.s.q_max or (q > self.s.q_max and e < 0) or (q < 0 and e > 0):
            self.integral = float(np.clip(trial, 0.0, self.s.q_max))
        return float(np.clip(self.s.kp * e + self.integral, 0.0, self.s.q_max))


@dataclass
class Record:
    """A generated experiment: logged rows plus the (unshipped) truth at the rows.

    ``time (n,)`` s; ``measured (n, 2)`` zone temperatures, NaN in dropouts; ``ambient (n,)``
    NaN off ambient rows; ``cooling (n, 2)`` W; ``true_states (n, 28)``; ``true_air (n, 2)``.
    """

    experiment: Experiment
    time: np.ndarray
    measured: np.ndarray
    ambient: np.ndarray
    cooling: np.ndarray
    true_states: np.ndarray
    true_air: np.ndarray


def _truth_model() -> NumpyModel:
    return NumpyModel.from_model(build_truth_model())


def record_experiment(exp: Experiment, truth: NumpyModel | None = None) -> Record:
    """Simulate the truth in closed loop with the PI controllers and log it (deterministic)."""
    truth = truth or _truth_model()
    rng = np.random.default_rng([BASE_SEED, int(exp.id)])
    ambient_fn = ambient_signal(exp, rng)
    t, k = logger_rows(rng)
    n = len(t)
    is_amb = k % AMBIENT_EVERY == 0
    amb_logged = np.where(is_amb, quantise(ambient_fn(t)), np.nan)
    amb_t, amb_v = t[is_amb], amb_logged[is_amb]
    noise = rng.normal(0.0, NOISE_SIGMA, size=(n, 2))
    gaps = dropout_mask(t, rng)

    p = truth.parameters(exp.parameters)
    names = truth.model.state_names
    i_air = [names.index(f"{z}.air.T") for z in ("zone1", "zone2")]
    ctrl = [PIController(ZONE_CONTROL[z], exp.setpoints[z]) for z in ("zone1", "zone2")]
    u = truth.start(p)
    states = np.empty((n, len(names)))
    cooling = np.zeros((n, 2))  # the unit starts switched off: Q_0 = 0
    measured = np.empty((n, 2))
    for i in range(n):
        states[i] = u
        measured[i] = quantise(u[i_air] + noise[i])
        if i == n - 1:
            break
        dt = t[i + 1] - t[i]
        cooling[i + 1] = np.round([c.update(y, dt) for c, y in zip(ctrl, measured[i])])
        x = piecewise_linear_inputs(
            [(amb_t, amb_v), (t[i : i + 2], cooling[i : i + 2, 0]), (t[i : i + 2], cooling[i : i + 2, 1])]
        )
        sol = solve_ivp(
            lambda s, y: truth.rhs(y, x(s), p), (t[i], t[i + 1]), u, method="Radau",
            jac=lambda s, y: truth.jac(y, x(s), p), rtol=1e-8, atol=1e-8,
        )
        if not sol.success:
            raise RuntimeError(f"experiment {exp.id}: truth integration failed at t = {t[i]} s: {sol.message}")
        u = sol.y[:, -1]
    measured[gaps] = np.nan
    return Record(exp, t, measured, amb_logged, cooling, states, states[:, i_air])


# -- writing -------------------------------------------------------------------------------------
def _fmt(value: float, decimals: int) -> str:
    return "" if not np.isfinite(value) else f"{value + 0.0:.{decimals}f}"


def to_csv_text(rec: Record) -> str:
    """The CSV text of a record: header ``COLUMNS``, empty fields where not measured."""
    lines = [",".join(COLUMNS)]
    for i in range(len(rec.time)):
        fields = [
            _fmt(rec.time[i], 1), _fmt(rec.measured[i, 0], 1), _fmt(rec.measured[i, 1], 1),
            _fmt(rec.ambient[i], 1), _fmt(rec.cooling[i, 0], 0), _fmt(rec.cooling[i, 1], 0),
        ]
        lines.append(",".join(fields))
    return "\n".join(lines) + "\n"


def generate(
    out: Path | str = TELEMETRY_DIR, experiments: Sequence[Experiment] = EXPERIMENTS, *, truth_out: Path | None = None
) -> list[Path]:
    """Write ``exp{ID}.csv`` for each experiment into ``out`` (created if needed); return the paths.

    ``truth_out``: also write the noise-free truth ``<ID>.csv`` of each experiment there (read only
    by the proving suite's scorer, ``benchmarks/discovery.py``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    truth = _truth_model()
    paths = []
    for exp in experiments:
        rec = record_experiment(exp, truth)
        path = out / exp.file
        path.write_text(to_csv_text(rec), encoding="ascii", newline="\n")
        paths.append(path)
        if truth_out is not None:
            Path(truth_out).mkdir(parents=True, exist_ok=True)
            tpath = Path(truth_out) / f"{exp.id}.csv"
            tpath.write_text(truth_csv_text(rec, truth.model.state_names), encoding="ascii", newline="\n")
            paths.append(tpath)
    return paths


def truth_csv_text(rec: Record, state_names: Sequence[str]) -> str:
    """The noise-free truth at the logged rows: ``time``, every state, every input (as the model sees
    it: the piecewise-linear interpolation of the logged samples) and ``term:<state>``, the concealed
    heat flow added to each air volume's heat balance (W)."""
    amb = np.isfinite(rec.ambient)
    ambient = np.interp(rec.time, rec.time[amb], rec.ambient[amb])
    leak = true_leakage(rec.true_air[:, 0], rec.true_air[:, 1])
    columns = {"time": rec.time, **{n: rec.true_states[:, i] for i, n in enumerate(state_names)},
               "ambient.T": ambient, "zone1.cooling.Q": rec.cooling[:, 0], "zone2.cooling.Q": rec.cooling[:, 1],
               "term:zone1.air.T": -leak, "term:zone2.air.T": leak}
    lines = [",".join(columns)]
    for i in range(len(rec.time)):
        lines.append(",".join(f"{v[i] + 0.0:.6g}" for v in columns.values()))
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python generate.py",
        description="Regenerate the synthetic cargo-box telemetry (deterministic).",
    )
    parser.add_argument("--out", type=Path, default=TELEMETRY_DIR, help=f"output folder (default: {TELEMETRY_DIR})")
    parser.add_argument("--truth", type=Path, default=None,
                        help=f"folder for the noise-free truth of every experiment (default: {TRUTH_DIR} when "
                             "--out is the default, none otherwise)")
    args = parser.parse_args(argv)
    truth = args.truth if args.truth is not None else (TRUTH_DIR if args.out == TELEMETRY_DIR else None)
    for path in (generate(args.out, truth_out=truth) if truth is not None else generate(args.out)):
        print(f"wrote {path} ({path.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
