"""The divergence rule: recorded ranges, boxes, first exits, and a solve held inside a box."""

from __future__ import annotations

import math

import torch

from physmend.simulate import odeint
from physmend.simulate.divergence import RANGE_MARGIN, box_of, first_exits, projected, recorded_range


def test_recorded_range_uses_fitted_experiments_and_has_a_floor() -> None:
    obs = torch.tensor([[[1.0, 5.0], [100.0, 5.0]], [[3.0, math.nan], [-50.0, 5.0]]], dtype=torch.float64)  # (T=2, B=2, k=2)
    lo, hi = recorded_range(obs, torch.tensor([True, False]))
    assert lo[0] == 1.0 and hi[0] == 3.0  # the second experiment (not fitted) decides nothing
    # a constant record still has a range: 10 % of its magnitude, centred
    assert math.isclose(float(lo[1]), 4.75) and math.isclose(float(hi[1]), 5.25)
    lo, hi = recorded_range(obs)  # all experiments
    assert lo[0] == -50.0 and hi[0] == 100.0


def test_box_is_the_range_widened_by_the_margin_and_unknown_ranges_are_unbounded() -> None:
    lo = torch.tensor([0.0, math.nan, 0.0], dtype=torch.float64)
    hi = torch.tensor([2.0, math.nan, 0.0], dtype=torch.float64)
    blo, bhi = box_of(lo, hi)
    assert float(blo[0]) == -2.0 * RANGE_MARGIN and float(bhi[0]) == 2.0 + 2.0 * RANGE_MARGIN
    assert blo[1] == -math.inf and bhi[1] == math.inf
    assert blo[2] == -math.inf and bhi[2] == math.inf  # recorded at exactly zero: no box


def test_first_exits_per_element_and_column() -> None:
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    values = torch.stack([torch.exp(10 * t), torch.ones_like(t)], -1)[:, None, :].repeat(1, 2, 1)  # (11, 2, 2)
    values[7, 1, 1] = math.nan  # a non-finite value is an exit
    first = first_exits(values, torch.tensor([-10.0, 0.0]), torch.tensor([100.0, 2.0]))
    assert first.tolist() == [[5, -1], [5, 7]]  # exp(10 t) > 100 from t = 0.5
    valid = torch.ones(11, 2, dtype=torch.bool)
    valid[4:, 0] = False  # the first element's record ends before it leaves
    assert first_exits(values, torch.tensor([-10.0, 0.0]), torch.tensor([100.0, 2.0]), valid).tolist() == [[-1, -1], [5, 7]]


def test_a_finite_time_blow_up_is_held_at_the_box_and_is_exact_inside_it() -> None:
    """du/dt = u² from u0 = 1 blows up at t = 1; held inside [0, 10] it is 1/(1 − t) until it reaches 10."""
    rhs = projected(lambda u, x: u**2, torch.tensor([0.0], dtype=torch.float64), torch.tensor([10.0], dtype=torch.float64))
    t = torch.linspace(0.0, 3.0, 31, dtype=torch.float64)
    u = odeint(lambda tt, uu: rhs(uu, None), torch.ones(1, 1, dtype=torch.float64), t, method="rodas4", rtol=1e-8, atol=1e-8)
    inside = t < 0.85
    torch.testing.assert_close(u[inside, 0, 0], 1.0 / (1.0 - t[inside]), rtol=1e-5, atol=1e-6)
    assert bool(torch.isfinite(u).all()) and float(u.max()) < 10.5
    assert float(u[-1, 0, 0]) >= 10.0 - 1e-9  # held at the edge after reaching it
