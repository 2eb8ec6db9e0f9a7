"""Unknown initial values: ``initial: {state: [low, high]}`` in the data config."""

from __future__ import annotations

import pytest

from physmend.data import DataError, load_experiments
from physmend.data.config import parse_data_config
from physmend.simulate import make_batch
from physmend.modeling import compile_model


def test_a_range_declares_an_unknown_initial_value_started_in_its_middle(cfg, model) -> None:
    cfg["experiments"][0]["initial"] = {"b.T": [18.0, 22.0], "a.T": 20.5}
    spec = parse_data_config(cfg, model).experiments[0]
    assert spec.initial_ranges == {"b.T": (18.0, 22.0)}
    assert spec.initial == {"b.T": 20.0, "a.T": 20.5}
    experiments = load_experiments(cfg, model)
    assert experiments[0].initial_ranges == {"b.T": (18.0, 22.0)} and experiments[1].initial_ranges == {}
    batch = make_batch(experiments, compile_model(model))
    assert batch.u0[0, model.state_names.index("b.T")].item() == 20.0


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([22.0, 18.0], r"experiment '1'.*initial range of 'b.T' must satisfy low < high, but got \[22, 18\]"),
        ([5.0, 5.0], r"initial range of 'b.T' must satisfy low < high, but got \[5, 5\] \(an empty range\)"),
        ([1.0, 2.0, 3.0], r"initial range of 'b.T' must be \[low, high\] \(two numbers\), but got \[1.0, 2.0, 3.0\]"),
        (["low", 2.0], r"initial range of 'b.T' must be a finite number, but got 'low'"),
    ],
)
def test_a_bad_range_is_one_clear_error(cfg, model, value, message) -> None:
    cfg["experiments"][0]["initial"] = {"b.T": value}
    with pytest.raises(DataError, match=message):
        parse_data_config(cfg, model)


def test_a_range_on_an_unknown_state_names_it(cfg, model) -> None:
    cfg["experiments"][0]["initial"] = {"c.T": [0.0, 1.0]}
    with pytest.raises(DataError, match=r"`initial` sets 'c.T', which is not a state of model 'rig'"):
        parse_data_config(cfg, model)
