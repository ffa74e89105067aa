"""Per-object caches of the measurement stage (a capture's pedestal and noise, a geometry's
lattice lookup), keyed by the live object itself.

Keying by ``id()`` alone is wrong: once an image or geometry is freed, a new one can be
allocated at the same address and read the old one's value (seen in the test suite: a
geometry's lattice lookup served to the next capture's geometry). Each entry keeps a weak
reference to its object and counts as a hit only while that reference still points to it.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any


class ObjectCache:
    """At most ``size`` values, each tied to one live object (by identity)."""

    def __init__(self, size: int = 1):
        self.size = int(size)
        self._items: dict[int, tuple[weakref.ref, Any]] = {}

    def get(self, obj: Any, make: Callable[[], Any]) -> Any:
        """The value cached for ``obj``, or ``make()`` stored for it."""
        key = id(obj)
        hit = self._items.get(key)
        if hit is not None and hit[0]() is obj:
            return hit[1]
        value = make()
        if len(self._items) >= self.size:
            self._items.clear()
        self._items[key] = (weakref.ref(obj), value)
        return value

    def clear(self) -> None:
        """Forget every entry."""
        self._items.clear()
