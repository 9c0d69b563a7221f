"""A mapping that keeps its most recently used entries: the viewer's caches.

An ``OrderedDict`` in recency order is the whole of it, so no caching library is needed.
"""

from __future__ import annotations

from collections import OrderedDict


class Recent:
    """The ``size`` most recently used entries; ``get`` gives ``None`` for a missing key."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"size must be at least 1, not {size}")
        self.size, self._items = size, OrderedDict()

    def get(self, key):
        value = self._items.get(key)
        if value is not None:
            self._items.move_to_end(key)
        return value

    def put(self, key, value) -> None:
        self._items[key] = value
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self._items.popitem(last=False)

    def __len__(self) -> int:
        return len(self._items)
