"""A mapping that keeps its most recently used entries: the viewer's caches.

An ``OrderedDict`` in recency order is the whole of it, so no caching library is needed. A
cache of textures is bounded by bytes as well as by count: a 4K material's prepared textures
take 168 MB, a 1K one's 10.5 MB. The server's two thread pools (frames, thumbnails) share the
library's caches, hence the lock.
"""

from __future__ import annotations

import threading
from collections import OrderedDict


def nbytes(value) -> int:
    """The bytes a cached value holds: a tensor's or an array's ``nbytes``, else 0."""
    return int(getattr(value, "nbytes", 0))


class Recent:
    """The ``size`` most recently used entries, and with ``max_bytes`` no more than that many
    bytes of them (:func:`nbytes`; the newest entry is kept whatever its size). ``get`` gives
    ``None`` for a missing key."""

    def __init__(self, size: int, max_bytes: int | None = None):
        if size < 1:
            raise ValueError(f"size must be at least 1, not {size}")
        if max_bytes is not None and max_bytes < 1:
            raise ValueError(f"max_bytes must be at least 1, not {max_bytes}")
        self.size, self.max_bytes = size, max_bytes
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key, value) -> None:
        with self._lock:
            old = self._items.pop(key, None)
            self._bytes += nbytes(value) - nbytes(old)
            self._items[key] = value
            while len(self._items) > self.size or (
                self.max_bytes is not None and self._bytes > self.max_bytes and len(self) > 1
            ):
                self._bytes -= nbytes(self._items.popitem(last=False)[1])

    def pop(self, key):
        """Remove the entry of ``key`` and give its value (``None`` when there is none)."""
        with self._lock:
            value = self._items.pop(key, None)
            self._bytes -= nbytes(value)
            return value

    @property
    def bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._items)
