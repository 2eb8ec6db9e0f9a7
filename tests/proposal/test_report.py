"""The proposal's small rules on their own: the RMSE of what was measured, and the report's lines
on terms, mechanisms and held-out experiments."""

from __future__ import annotations

import math
from types import SimpleNamespace

import sympy as sp
import torch

from physmend.proposal.fits import rmse
from physmend.proposal.report import MIN_MECHANISM_R2, markdown


def test_the_rmse_counts_what_was_measured() -> None:
    assert rmse(torch.tensor([3.0, float("nan"), -3.0])) == 3.0
    assert math.isnan(rmse(torch.tensor([float("nan")])))


def test_the_report_names_a_mechanism_only_above_the_bar_and_the_held_out_gain() -> None:
    T = sp.Symbol("box.T")
    written = SimpleNamespace(equations={}, parameters=[], units={"box.T": "K"})
    mechanism = {"name": "convective exchange", "explanation": "heat to the room", "r2": MIN_MECHANISM_R2 + 0.05}
    terms = [{"state": "box.T", "term": "c1*box.T", "sympy": sp.Float(-0.1) * T, "constants": {"c1": -0.1},
              "unit": "W", "equation": "", "owner": "box", "mean_abs": 2.0, "max_abs": 3.0, "mechanisms": [mechanism]},
             {"state": "box.Q", "term": "c1", "sympy": sp.Float(1.0), "constants": {"c1": 1.0}, "unit": "W",
              "equation": "", "owner": "box", "mean_abs": 1.0, "max_abs": 1.0,
              "mechanisms": [{**mechanism, "r2": MIN_MECHANISM_R2 - 0.5}]}]
    rows = [{"experiment": e, "role": role, "output": "box.T", "before": 2.0, "after": 1.0, "noise": 0.5,
             "improvement": gain} for e, role, gain in (("a", "train", 2.0), ("b", "test", 4.0), ("c", "test", 3.0))]
    report, math_ = markdown("physmend proposal — model box", "RUN", written, "s", terms, {}, rows, [], [],
                             [SimpleNamespace(id="a"), SimpleNamespace(id="b"), SimpleNamespace(id="c")])
    assert report.startswith("# physmend proposal — model box\n\nSource: symbolic run RUN.")
    assert "- suggested mechanism: **convective exchange** — heat to the room" in report
    assert "- no catalogued mechanism matches this form (closest: convective exchange, R² 0.40)" in report
    assert "RMSE improved 3.0× to 4.0×." in report and "![fit c](plots/fit_c.png)" in report
    assert set(math_) == {"c1*box.T", "c1"} and all("sympy" not in t for t in terms)  # JSON-ready
