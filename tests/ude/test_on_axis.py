"""A group of experiments solved apart (a failing test record) still fills every row of the shared
time axis its experiments span: the other experiments' sample times are interpolated, not NaN."""

from __future__ import annotations

import math

import torch

from physmend.ude.reference import on_axis


def test_rows_of_other_experiments_are_interpolated_and_rows_outside_are_nan() -> None:
    t_from = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)
    values = torch.tensor([[0.0, 10.0], [2.0, 20.0], [6.0, 40.0]], dtype=torch.float64)[:, None, :]  # (T, 1, 2)
    t_to = torch.tensor([0.0, 0.5, 1.0, 2.0, 3.0, 4.0], dtype=torch.float64)  # 0.5, 2 and 4: another record's samples
    out = on_axis(values, t_from, t_to)
    assert out.shape == (6, 1, 2)
    assert out[:5, 0, 0].tolist() == [0.0, 1.0, 2.0, 4.0, 6.0]
    assert out[3, 0, 1].item() == 30.0
    assert all(math.isnan(v) for v in out[5, 0].tolist())  # past the group's last sample
