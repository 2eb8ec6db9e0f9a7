"""Users' projects whose model as written diverges within the record, written only through the
public API into a tmp folder, with telemetry from a 'truth' that has the term the model lacks.

- ``growth``: logistic growth ``dx/dt = r·x·(1 − x/K) + u`` of a colony fed at ``u``, and the
  oxygen ``c`` of its medium, ``dc/dt = kla·(c_sat − c) − q·x·c``; the model as written lacks the
  crowding ``−r·x²/K`` and grows exponentially, by ``exp(r·T) ≈ 1e8`` over the record (time in
  days), and its oxygen uptake then turns stiff (time constant ``1/(q·x)``).
- ``blowup``: ``dx/dt = a·x² − c·x³``; the model as written lacks the sink ``−c·x³`` and blows up
  in finite time ``1/(a·x0)``, a fifth into the record (time in the model's own unit ``tu``).

Every state is measured (with noise); three experiments (train, validation, test).
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.integrate

GROWTH_MODEL = textwrap.dedent(
    '''
    from physmend.modeling import Model

    def build():
        m = Model("growth", description="a colony growing at a constant rate")
        x = m.state("colony.x", start=1.0, unit="kcells")
        r = m.parameter("colony.r", 0.6, unit="1/d")
        c = m.state("medium.c", start=8.0, unit="mg/L")
        kla = m.parameter("medium.kla", 2.0, unit="1/d")
        c_sat = m.parameter("medium.c_sat", 8.0, unit="mg/L")
        q = m.parameter("colony.q", 0.01, unit="1/(kcells.d)")
        feed = m.input("feed.u", unit="kcells/d")
        m.equation(m.der(x), r * x + feed, owner="colony")
        m.equation(m.der(c), kla * (c_sat - c) - q * x * c, owner="medium")
        m.output("colony.x", x, unit="kcells")
        m.output("medium.c", c, unit="mg/L")
        return m
    '''
)

BLOWUP_MODEL = textwrap.dedent(
    '''
    from physmend.modeling import Model

    def build():
        m = Model("ignition", description="a self-accelerating reaction")
        x = m.state("fuel.x", start=1.0, unit="mol")
        a = m.parameter("fuel.a", 0.5, unit="1/(mol.tu)")
        m.equation(m.der(x), a * x**2, owner="fuel")
        m.output("fuel.x", x, unit="mol")
        return m
    '''
)

GROWTH_R, GROWTH_K = 0.6, 100.0  # 1/d, kcells
BLOWUP_A, BLOWUP_C = 0.5, 0.1  # 1/(mol.tu), 1/(mol².tu)
RECORD = {"growth": (30.0, 0.25, "d"), "blowup": (10.0, 0.1, "tu")}  # span, interval, time unit


def _truth(kind: str, x0: float, t: np.ndarray, feed: np.ndarray) -> np.ndarray:
    """States ``(n, T)`` of the truth at ``t``."""
    def rhs(tt: float, y: np.ndarray) -> list[float]:
        x = y[0]
        if kind == "growth":
            return [GROWTH_R * x * (1 - x / GROWTH_K) + float(np.interp(tt, t, feed)), 2.0 * (8.0 - y[1]) - 0.01 * x * y[1]]
        return [BLOWUP_A * x**2 - BLOWUP_C * x**3]

    start = [x0, 8.0] if kind == "growth" else [x0]
    sol = scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), start, t_eval=t, rtol=1e-9, atol=1e-9, method="LSODA")
    assert sol.success
    return sol.y


def write_project(root: Path, kind: str = "growth", n_samples: int | None = None) -> tuple[Path, str]:
    """The project ``kind`` (``growth`` | ``blowup``) under ``root``; returns ``(config dir, name)``.

    ``n_samples``: samples per experiment (default: the whole record at its interval).
    """
    rng = np.random.default_rng(3)
    span, dt, unit = RECORD[kind]
    (root / f"{kind}.py").write_text(GROWTH_MODEL if kind == "growth" else BLOWUP_MODEL)
    data = root / "recordings"
    data.mkdir(parents=True, exist_ok=True)
    state = "colony.x" if kind == "growth" else "fuel.x"
    entries = []
    for i, (x0, role) in enumerate([(1.0, "train"), (1.5, "validation"), (0.8, "test")], 1):
        t = np.arange(0.0, span + dt / 2, dt)
        if n_samples is not None:
            t = np.linspace(0.0, span, n_samples)
        feed = 0.2 * (1.0 + np.sin(0.5 * t + i))
        truth = _truth(kind, x0, t, feed)
        noisy = [y + rng.normal(0.0, 0.003 * float(np.abs(y).max()), t.size) for y in truth]
        columns = {"time": t, "count": noisy[0]}
        if kind == "growth":
            columns.update({"oxygen": noisy[1], "feed.u": feed})
        pd.DataFrame(columns).to_csv(data / f"e{i}.csv", index=False)
        entries.append(f"  - {{id: e{i}, file: e{i}.csv, role: {role}, initial: {{{state}: {x0}}}}}\n")
    conf = root / "conf"
    (conf / "model").mkdir(parents=True, exist_ok=True)
    (conf / "data").mkdir(exist_ok=True)
    (conf / "model" / f"{kind}.yaml").write_text(f"builder: {root / (kind + '.py')}:build\noptions: {{}}\n")
    (conf / "data" / f"{kind}.yaml").write_text(
        f"name: {kind}\nroot: {data}\ntime_column: time\ntime_unit: {unit}\n"
        f"columns: {{{state}: count{', medium.c: oxygen' if kind == 'growth' else ''}}}\nexperiments:\n" + "".join(entries)
    )
    return conf, kind


if __name__ == "__main__":  # a project to try by hand: python tests/diverging_projects.py DIR growth|blowup
    import sys

    conf, name = write_project(Path(sys.argv[1]), sys.argv[2] if len(sys.argv) > 2 else "growth")
    print(f"physmend diagnose --config-dir {conf} model={name} data={name}")
