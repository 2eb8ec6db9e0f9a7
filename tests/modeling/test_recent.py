"""``Recent``: what a process made, kept up to a count, the most recently used kept."""

from __future__ import annotations

import pytest

from physmend.modeling.recent import Recent


def test_the_least_recently_used_goes_first_and_a_failure_keeps_nothing() -> None:
    made: list[str] = []

    def maker(key: str):  # noqa: ANN202
        return lambda: made.append(key) or key.upper()

    kept: Recent[str] = Recent(2)
    assert kept.get("a", maker("a")) == "A" and kept.get("b", maker("b")) == "B"
    assert kept.get("a", maker("a")) == "A"  # kept: not made again, and now the most recent
    kept.get("c", maker("c"))  # "b" goes: least recently used
    assert len(kept) == 2 and made == ["a", "b", "c"]
    kept.get("a", maker("a"))
    kept.get("b", maker("b"))
    assert made == ["a", "b", "c", "b"]

    def fails() -> str:
        raise ValueError("not made")

    with pytest.raises(ValueError, match="not made"):
        kept.get("d", fails)
    assert len(kept) == 2
    kept.clear()
    assert len(kept) == 0
