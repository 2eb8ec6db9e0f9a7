"""Two training configurations: a parameter seen at two values only.

A heated pipe section of length ``pipe.L`` (2 m and 4 m in training, 6 m held out) loses heat to
wind the model leaves out. Where the loss scales with the length (``−c·L·v``), the formula must
carry the length, so that it holds at 6 m; where it does not (``−c·v``: the length only labels the
two experiments), the formula must not use it. The network never takes a two-valued parameter (it
could memorise the experiments with it); the formula search may, only as a scale with one shared
constant, and the recordings of both experiments decide.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.integrate
import yaml

from physmend.cli import main

MODEL = textwrap.dedent(
    '''
    from physmend.modeling import Model

    def build():
        m = Model("pipe", description="a heated pipe section")
        T = m.state("pipe.T", start=300.0, unit="K")
        L = m.parameter("pipe.L", 3.0, unit="m")
        C = m.parameter("pipe.C", 2.0e4, unit="J/K")
        UA = m.parameter("pipe.UA", 5.0, unit="W/K")
        Ta = m.input("room.T", unit="K")
        P = m.input("heater.P", unit="W")
        m.input("wind.v", unit="m/s")
        m.equation(L * C * m.der(T), P - L * UA * (T - Ta), owner="pipe")
        m.output("pipe.T", T, unit="K")
        return m
    '''
)

LOSS = 6.0  # W per (m · m/s)


def _record(length: float, seed: int, scales_with_length: bool) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 4 * 3600.0, 60.0)
    levels = rng.uniform(100.0, 400.0, 10) * length
    P = levels[np.minimum((t // 1500).astype(int), 9)]
    v = 2.0 + 1.5 * np.sin(2 * np.pi * t / 3000.0 + seed) + rng.uniform(0, 1.0)
    Ta = 290.0 + 2.0 * np.sin(2 * np.pi * t / 9000.0)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        p, w, a = (np.interp(tt, t, z) for z in (P, v, Ta))
        loss = LOSS * (length if scales_with_length else 3.0) * w
        return [(p - length * 5.0 * (y[0] - a) - loss) / (length * 2.0e4)]

    sol = scipy.integrate.solve_ivp(rhs, (t[0], t[-1]), [300.0], t_eval=t, rtol=1e-9, atol=1e-9, max_step=60.0)
    return pd.DataFrame({"time": t, "pipe.T": sol.y[0] + rng.normal(0, 0.05, t.size), "room.T": Ta,
                         "heater.P": P, "wind.v": v})


def _project(root: Path, scales_with_length: bool) -> Path:
    (root / "pipe.py").write_text(MODEL)
    rows = []
    for i, (length, role) in enumerate([(2.0, "train"), (4.0, "train"), (6.0, "test")]):
        _record(length, i, scales_with_length).to_csv(root / f"r{i}.csv", index=False)
        rows.append({"id": f"r{i}", "file": f"r{i}.csv", "role": role, "parameters": {"pipe.L": length},
                     "initial": {"pipe.T": 300.0}})
    conf = root / "conf"
    (conf / "model").mkdir(parents=True)
    (conf / "data").mkdir()
    (conf / "model" / "pipe.yaml").write_text(f"builder: {root / 'pipe.py'}:build\noptions: {{}}\n")
    (conf / "data" / "pipe.yaml").write_text(yaml.safe_dump({"name": "pipe", "root": str(root), "time_column": "time",
                                                              "experiments": rows}))
    return conf


@pytest.mark.slow
@pytest.mark.parametrize("scales_with_length", [True, False], ids=["loss-per-length", "length-only-labels"])
def test_a_two_valued_parameter_enters_the_formula_only_where_the_data_say(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        scales_with_length: bool, reset_mlflow: None) -> None:
    conf = _project(tmp_path, scales_with_length)
    monkeypatch.chdir(tmp_path)
    rc = main(["discover", "--config-dir", str(conf), "model=pipe", "data=pipe", "discover.n_trials=1",
               "train.epochs=60", "train.eval_every=20", "ude.depth=1", "symbolic.refit_epochs=10"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    sym = out.out[out.out.index("physmend symbolic"):]
    formula = next(line for line in sym.splitlines() if line.startswith("pipe.T: + "))
    assert "wind.v" in formula, sym
    if scales_with_length:
        assert "pipe.L" in formula, sym
        # the held-out 6 m pipe: the corrected model fits far better than the model as written
        prop = out.out[out.out.index("physmend propose"):]
        assert "r2" in prop
    else:
        assert "pipe.L" not in formula, sym
