"""Times are written in the unit that suits the record; a declared non-second unit is never converted."""

from __future__ import annotations

import numpy as np

from physmend.explain.clock import axis, clock


def test_seconds_are_shown_in_the_unit_that_suits_the_record() -> None:
    assert clock(5400.0, 12 * 3600) == "1.5 h"
    assert clock(0.25, 2.0) == "0.2 s"
    assert clock(3 * 86400, 10 * 86400) == "3.00 d"
    values, divisor, label = axis(np.array([0.0, 600.0, 1200.0]))
    assert (label, divisor) == ("min", 60.0) and values[-1] == 20.0


def test_a_declared_time_unit_is_shown_as_it_is() -> None:
    assert clock(7200.0, 30000.0, "tu") == "7200.0 tu"  # not hours: tu are not seconds
    values, divisor, label = axis(np.array([0.0, 15.0, 30.0]), "tu")
    assert (label, divisor) == ("tu", 1.0) and values[1] == 15.0
