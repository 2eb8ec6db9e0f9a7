"""When training stops: at a cycle's end once the model has had a good checkpoint long enough."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from physmend.settings import SettingError, TrainSettings, shipped_default
from physmend.ude.schedule import cycle_of, stops_at


def test_a_model_that_could_never_be_simulated_restarts_and_one_that_just_recovered_gets_a_full_cycle() -> None:
    epochs = 120
    assert [cycle_of(e, epochs) for e in (0, 1, 120, 121, 240, 241)] == [0, 0, 0, 1, 1, 2]
    assert not stops_at(100, epochs, 0)  # inside the first cycle: never
    assert stops_at(121, epochs, 0)  # good in the first cycle: no restart
    assert not stops_at(121, epochs, None)  # never good: the schedule starts again
    assert not stops_at(241, epochs, 1)  # first good in the restarted cycle: one more full cycle
    assert stops_at(361, epochs, 1)
    assert not stops_at(250, epochs, 1)  # not at a cycle's end


def test_restarts_is_a_count_whose_default_is_the_shipped_one() -> None:
    assert TrainSettings.build(OmegaConf.create({"restarts": 0})).cycles == 1
    assert TrainSettings.build(OmegaConf.create({})).restarts == shipped_default("train", "restarts") == 2
    with pytest.raises(SettingError, match=r"train.restarts must be a whole number ≥ 0, but got -1"):
        TrainSettings.build(OmegaConf.create({"restarts": -1}))
