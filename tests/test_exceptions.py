"""Every error that means "your input is wrong" is a physmend.PhysmendError (one except clause in a notebook)."""

from __future__ import annotations

import pytest

import physmend
from physmend.errors import USER_ERROR_NAMES, is_user_error, user_errors


def test_every_user_error_is_a_physmend_error_and_keeps_its_old_base() -> None:
    classes = user_errors()
    assert len(classes) == len(USER_ERROR_NAMES) >= 11
    for cls in classes:
        assert issubclass(cls, physmend.PhysmendError), cls
        assert issubclass(cls, (ValueError, RuntimeError)), cls  # older except clauses still catch it
        assert is_user_error(cls("x"))


def test_a_bad_run_id_from_python_is_caught_as_a_physmend_error(tmp_path) -> None:
    with pytest.raises(physmend.PhysmendError, match="no-such-run"):
        physmend.mask("no-such-run", tracking={"uri": f"sqlite:///{tmp_path / 'mlflow.db'}"})


def test_a_setting_against_its_rule_is_a_user_error_said_in_one_line() -> None:
    from physmend.settings import SettingError, TrainSettings

    with pytest.raises(SettingError, match=r"train.epochs must be a whole number ≥ 1, but got 0") as caught:
        TrainSettings.build({"epochs": 0})
    assert is_user_error(caught.value)  # the CLI prints the message, no traceback (e.g. a stored run's settings)
    assert SettingError in user_errors()
