"""The sensitivity's findings in words (:func:`physmend.symbolic.sensitivity.report`): the inputs
passed on are starred, groups are listed only where some input has company."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from physmend.symbolic.sensitivity import Sensitivity, report


def _found(group_r: float | None, members: list[str]) -> Sensitivity:
    group = SimpleNamespace(representative="room.T", members=members)
    return Sensitivity(kept=["room.T"], inputs=["room.T", "wall.T", "heater.P"],
                       ranking=[("room.T", 0.9), ("wall.T", 0.8), ("heater.P", 0.1)], grouped=[(group, 0.95)],
                       chosen=["room.T"], how="top 1 by sensitivity", matrix=np.ones((1, 3)), group_r=group_r)


def test_the_report_stars_what_is_passed_on_and_lists_groups_with_company() -> None:
    text = report(_found(0.95, ["room.T", "wall.T"]), "mask run R")
    assert text.startswith("# physmend sensitivity — source mask run R\n")
    assert "  1. ★ room.T  0.900" in text and "  2.   wall.T  0.800" in text
    assert "  1. ★ room.T  0.950  (with wall.T)" in text
    assert text.endswith("Passed to symbolic regression (top 1 by sensitivity): room.T")
    assert "Ranked as groups" not in report(_found(0.95, ["room.T"]), "mask run R")
    assert "Ranked as groups" not in report(_found(None, ["room.T", "wall.T"]), "mask run R")
    assert _found(None, ["room.T"]).record()["groups"] == [{"representative": "room.T", "members": ["room.T"],
                                                             "score": 0.95}]
