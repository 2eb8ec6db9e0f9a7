"""What this process made most recently, kept up to a count: a model, a solved block, a function."""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

V = TypeVar("V")


class Recent(Generic[V]):
    """At most ``kept`` values by key, the most recently used kept (a bound on memory, not on results)."""

    def __init__(self, kept: int) -> None:
        self.kept = kept
        self._values: dict[Hashable, V] = {}

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        """The value kept for ``key``, else ``make()``'s, now kept (an exception from ``make`` keeps nothing)."""
        value = self._values.pop(key, None)
        if value is None:
            value = make()
            while len(self._values) >= self.kept:
                self._values.pop(next(iter(self._values)))
        self._values[key] = value
        return value

    def clear(self) -> None:
        self._values.clear()

    def __len__(self) -> int:
        return len(self._values)
