"""Objects made from a data object, keyed by its identity: the host-structure
cache (`mi_amr.structures.cache`) and the device copies of a volume's values
(`mi_amr.data.device_values`).

Host structures (the blocks made from per-cell records, bricks, brick trees
and their value ranges, the kd-tree's input grid, value masks) depend only
on the data and on build options, not on the transfer function. Media that
share one data object (a scene loaded twice, a benchmark that renders the
same cells with several structures) build each of them once.

Entries are keyed by the *identity* of the data object (two equal arrays
loaded twice are two keys) and a hashable key of the options; they go away
with the data object (a weak finalizer), and nothing is stored on the data
object itself.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any, Callable, Hashable


class IdentityCache:
    """Objects made from a data object, per data object and key."""

    def __init__(self):
        self._entries: dict[int, dict[Hashable, Any]] = {}
        self._lock = threading.Lock()

    def get(self, data, key: Hashable, make: Callable[[], Any]):
        """The object ``key`` of ``data``, made by ``make()`` the first time."""
        slot = self._slot(data)
        if key not in slot:
            slot[key] = make()
        return slot[key]

    def peek(self, data, key: Hashable, default=None):
        """The object ``key`` of ``data`` if it was made, else ``default``."""
        return self._entries.get(id(data), {}).get(key, default)

    def keys(self, data) -> set:
        """The keys made so far for ``data``."""
        return set(self._entries.get(id(data), {}))

    def ids(self) -> set:
        """Identities (``id``) of the data objects that have entries."""
        return set(self._entries)

    def _slot(self, data) -> dict:
        with self._lock:
            slot = self._entries.get(id(data))
            if slot is None:
                slot = self._entries[id(data)] = {}
                # the id may be reused once the object is gone: drop its entries then
                weakref.finalize(data, self._entries.pop, id(data), None)
            return slot

    def put(self, data, key: Hashable, value):
        """Make ``value`` the object ``key`` of ``data``."""
        self._slot(data)[key] = value
