"""One short noisy record: 36 samples of two measured species, a reaction ``A + B →`` missing from
both balances. The recorded mismatch gives a handful of window means, so each formula is chosen by
simulating the corrected model over every training sample; the product of the two states must be
chosen in both equations, and the held-out run must improve."""

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
        m = Model("tank", description="a stirred tank with a feed of A and B")
        a = m.state("tank.A", start=1.0, unit="mol/L")
        b = m.state("tank.B", start=1.0, unit="mol/L")
        k = m.parameter("tank.k", 0.05, unit="1/min")
        qa = m.input("feed.a", unit="mol/(L.min)")
        m.equation(m.der(a), qa - k * a, owner="tank")
        m.equation(m.der(b), 0.04 - k * b, owner="tank")
        m.output("tank.A", a, unit="mol/L")
        m.output("tank.B", b, unit="mol/L")
        return m
    '''
)

RATE = 0.03  # L/(mol·min): the reaction A + B → C the model leaves out


def _record(a0: float, b0: float, seed: int, n: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    t = np.sort(np.concatenate([[0.0], rng.uniform(0.5, 60.0, n - 1)]))
    knots = np.arange(0.0, 61.0, 10.0)
    feed = rng.uniform(0.0, 0.12, knots.size)

    def rhs(tt: float, y: np.ndarray) -> list[float]:
        q = float(np.interp(tt, knots, feed))
        r = RATE * y[0] * y[1]
        return [q - 0.05 * y[0] - r, 0.04 - 0.05 * y[1] - r]

    sol = scipy.integrate.solve_ivp(rhs, (0.0, 60.0), [a0, b0], t_eval=t, rtol=1e-10, atol=1e-10)
    return pd.DataFrame({"time": t, "tank.A": sol.y[0] + rng.normal(0, 0.01, n),
                         "tank.B": sol.y[1] + rng.normal(0, 0.01, n), "feed.a": np.interp(t, knots, feed)})


@pytest.mark.slow
def test_one_short_record_gets_the_product_of_two_states_in_both_equations(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], reset_mlflow: None) -> None:
    (tmp_path / "tank.py").write_text(MODEL)
    rows = []
    for i, (a0, b0, role, n) in enumerate([(0.3, 2.0, "train", 36), (1.5, 0.6, "test", 36)]):
        _record(a0, b0, i, n).to_csv(tmp_path / f"r{i}.csv", index=False)
        rows.append({"id": f"r{i}", "file": f"r{i}.csv", "role": role, "initial": {"tank.A": a0, "tank.B": b0}})
    conf = tmp_path / "conf"
    (conf / "model").mkdir(parents=True)
    (conf / "data").mkdir()
    (conf / "model" / "tank.yaml").write_text(f"builder: {tmp_path / 'tank.py'}:build\noptions: {{}}\n")
    (conf / "data" / "tank.yaml").write_text(yaml.safe_dump({"name": "tank", "root": str(tmp_path),
                                                              "time_column": "time", "experiments": rows}))
    monkeypatch.chdir(tmp_path)
    rc = main(["discover", "--config-dir", str(conf), "model=tank", "data=tank", "discover.n_trials=1",
               "train.epochs=100", "train.eval_every=20", "ude.depth=1", "symbolic.refit_epochs=10"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    sym = out.out[out.out.index("# physmend symbolic"):]
    assert sym.count("Rule 'simulated' (the training records give only") == 2, sym
    for state in ("tank.A", "tank.B"):
        formula = next(line for line in sym.splitlines() if line.startswith(f"{state}: + "))
        assert "tank.A*tank.B" in formula.replace(" ", ""), sym
    held = next(line for line in out.out.splitlines() if line.startswith("Held-out experiments"))
    assert float(held.split("improved ")[1].split("×")[0]) >= 5.0, held
